// Wrong-merge bench of mapmerge::align on pairs that share nothing (issue 3: "rejecting is
// always better than a wrong transform"). Each case is a part of one real map and a part of a
// map of another building, or two disjoint halves of one map, the second moved by a random
// transform. Any accepted result of such a pair is a wrong merge (two halves placed where they
// belong excepted). fr_078_tidyup (5 cm) meets fr_079 (5 cm), geb079 (8 cm) and fr_079
// coarsened to 20 cm (fr_079 and geb079 are one corridor, so never paired): the validation's
// tolerances are also tried on mixed-resolution pairs, which the accuracy bench (bench_align)
// never makes. Each pair runs through every search the product makes:
//   whole  - the whole-map search without a rescue (the server's first search);
//   blocks - the block-by-block search without a rescue (the server's fallback);
//   rescue - the rescue's dense search alone (the server's idle rescue);
//   merge  - the whole-map search with its rescue (`mapmerge merge`'s default).
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <random>
#include <sstream>

#include <CLI/CLI.hpp>
#include <Eigen/Geometry>

#include "bench_common.hpp"
#include "mapmerge/align/align.hpp"
#include "mapmerge/map/crop.hpp"
#include "mapmerge/map/map_io.hpp"

namespace ma = mapmerge::align;
using mapmerge::bench::fmt;
using Clock = std::chrono::steady_clock;

namespace {

struct Map {
  std::string name;
  std::string building;  ///< maps of one building share places (fr_079 and geb079: one corridor)
  std::unique_ptr<octomap::OcTree> tree;
};

/// A part of a map: the larger box of an overlap cut (about half the map and more), along a
/// random axis.
struct Part {
  std::string name;
  std::unique_ptr<octomap::OcTree> tree;
};

struct Search {
  std::string name;
  ma::AlignConfig config;
  bool rescue_only = false;
};

struct Outcome {
  std::string pair, search;
  bool accepted = false;
  bool wrong = false;  ///< accepted, and not where the part belongs
  double fitness = 0, overlap = 0, inlier_share = 0, seconds = 0;
  double limit = 0;  ///< validate.max_fitness x the coarser map's resolution [m]
  std::string reason;
};

std::vector<Search> searches(const ma::AlignConfig& base) {
  ma::AlignConfig whole = base;
  whole.rescue.enabled = false;
  whole.submodels.enabled = false;
  ma::AlignConfig blocks = whole;
  blocks.submodels.enabled = true;
  ma::AlignConfig merge = base;
  merge.submodels.enabled = false;
  merge.rescue.enabled = true;
  return {{"whole", whole}, {"blocks", blocks}, {"rescue", whole, true}, {"merge", merge}};
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"mapmerge_bench_strangers: wrong merges on pairs of real map parts that share nothing"};
  const std::string data = MAPMERGE_DATA_DIR;
  int trials = 2;
  unsigned seed = 1;
  std::string out_path, config_path;
  app.add_option("--trials", trials, "random parts and transforms per ordered pair of maps");
  app.add_option("--seed", seed, "random seed");
  app.add_option("--config", config_path, "YAML config (the searches are varied from it)");
  app.add_option("--out", out_path, "also write the Markdown report here");
  CLI11_PARSE(app, argc, argv);
  try {
    const ma::AlignConfig base = config_path.empty() ? ma::AlignConfig{} : ma::load_align_config(config_path);
    std::vector<Map> maps;
    for (const auto& [file, building] : {std::pair{"fr_078_tidyup.bt", "078"}, std::pair{"fr_079.bt", "079"},
                                         std::pair{"geb079.bt", "079"}}) {
      maps.push_back({file, building, mapmerge::read_octree_file(data + "/" + file)});
    }
    maps.push_back({"fr_079.bt @0.20m", "079", mapmerge::coarsen(*maps[1].tree, 4)});
    std::mt19937 rng(seed);
    std::uniform_real_distribution<double> yaw(-180.0, 180.0), tilt(-5.0, 5.0), shift(-10.0, 10.0), lift(-0.5, 0.5),
        share(0.1, 0.4);
    std::uniform_int_distribution<int> axis(0, 1);
    const auto part_of = [&](const Map& m, bool first, const Eigen::Matrix4d& T) {
      const int a = axis(rng);
      const auto [one, other] = mapmerge::overlap_cut(*m.tree, a, share(rng));
      return Part{m.name + (first ? " first" : " second") + " part along " + (a == 0 ? "x" : "y"),
                  mapmerge::crop_and_transform(*m.tree, first ? one : other, Eigen::Isometry3d(T))};
    };
    const std::vector<Search> all = searches(base);
    std::vector<Outcome> outcomes;
    for (std::size_t i = 0; i < maps.size(); ++i) {
      for (std::size_t j = 0; j < maps.size(); ++j) {
        // Another building, or two disjoint halves of one map (an overlap cut of 0). fr_079,
        // geb079 (the same corridor, another dataset) and the coarsened fr_079 are one building.
        if (i != j && maps[i].building == maps[j].building) continue;
        for (int t = 0; t < trials; ++t) {
          const Eigen::Matrix4d T = mapmerge::paper_transform(shift(rng), shift(rng), lift(rng), tilt(rng), tilt(rng),
                                                              yaw(rng));
          Part target{}, source{};
          if (i == j) {
            const int a = axis(rng);
            auto [one, other] = mapmerge::overlap_cut(*maps[i].tree, a, 0.0);
            other.min()(a) += maps[i].tree->getResolution();  // (both boxes end at the median voxel)
            target = {maps[i].name + " one half along " + (a == 0 ? "x" : "y"),
                      mapmerge::crop_and_transform(*maps[i].tree, one, Eigen::Isometry3d::Identity())};
            source = {"the other half", mapmerge::crop_and_transform(*maps[i].tree, other, Eigen::Isometry3d(T))};
          } else {
            target = part_of(maps[i], true, Eigen::Matrix4d::Identity());
            source = part_of(maps[j], false, T);
          }
          const std::string pair = target.name + " <- " + source.name;
          // Two halves of one map touch: placed where they belong, they are no wrong merge.
          const bool halves = i == j;
          const ma::PreparedMap pt = ma::prepare_map(*target.tree, base), ps = ma::prepare_map(*source.tree, base);
          for (const Search& s : all) {
            const auto t0 = Clock::now();
            const ma::AlignResult r = s.rescue_only ? ma::rescue(pt, ps, s.config) : ma::align(pt, ps, s.config);
            const bool where_it_belongs = halves && mapmerge::bench::errors(r.T_target_source, T).success();
            Outcome o{pair, s.name, r.accepted, r.accepted && !where_it_belongs,
                      r.fitness, r.overlap, r.inlier_share, std::chrono::duration<double>(Clock::now() - t0).count(),
                      s.config.validate.max_fitness *
                          std::max(target.tree->getResolution(), source.tree->getResolution()),
                      r.reason};
            std::cerr << pair << " [" << s.name << "]: "
                      << (o.wrong ? "WRONG MERGE" : o.accepted ? "accepted where it belongs" : "refused") << " f "
                      << fmt(o.fitness, 4) << " ovl " << fmt(o.overlap) << " share " << fmt(o.inlier_share) << " "
                      << fmt(o.seconds, 2) << " s" << (o.accepted ? "" : " (" + o.reason + ")") << "\n";
            outcomes.push_back(std::move(o));
          }
        }
      }
    }
    std::ostringstream md;
    md << "# Wrong-merge bench: pairs that share nothing\n\n"
       << "Generated by `mapmerge_bench_strangers` (bench/align/bench_strangers.cpp), seed " << seed << ", " << trials
       << " trial(s) per ordered pair of maps. Each case: a part of one map (the larger box of an overlap cut at "
          "10-40 %, along x or y) and a part of another building's map (fr_078_tidyup against fr_079, geb079 and fr_079 "
          "coarsened to 20 cm; fr_079 and geb079 are one corridor) moved by a random transform (yaw over the "
          "full circle, roll/pitch up to 5°, |x|,|y| up to 10 m), or two disjoint halves of one building's map. "
          "Nothing is shared, so every accepted result is a wrong merge, except two halves of one building placed "
          "where they belong (they touch: rotation within 5° and translation within 0.3 m of the truth). Searches: `whole` (whole map, no "
          "rescue: the server's first search), `blocks` (block by block, no rescue: its fallback), `rescue` (the "
          "rescue's dense search alone: its idle rescue), `merge` (whole map with its rescue: `mapmerge merge`).\n\n"
       << "| search | cases | wrong merges | median t [s] |\n|---|---|---|---|\n";
    for (const Search& s : all) {
      std::vector<double> t;
      std::size_t wrong = 0;
      for (const Outcome& o : outcomes) {
        if (o.search != s.name) continue;
        t.push_back(o.seconds);
        wrong += o.wrong;
      }
      std::sort(t.begin(), t.end());
      md << "| " << s.name << " | " << t.size() << " | " << wrong << " | " << fmt(t.empty() ? NAN : t[t.size() / 2], 2)
         << " |\n";
    }
    // How close the strangers came: fitness over its limit, for the refused cases with a finite
    // fitness, and for those that also pass the free-space test (the inlier share), so would be
    // accepted on fitness alone: the margin the fitness test keeps on its own.
    const auto closest = [&](bool passing_free_space) {
      const Outcome* best = nullptr;
      for (const Outcome& o : outcomes) {
        if (o.accepted || !std::isfinite(o.fitness) || o.fitness <= 0.0) continue;
        if (passing_free_space && o.inlier_share < base.validate.min_inlier_share) continue;
        if (best == nullptr || o.fitness / o.limit < best->fitness / best->limit) best = &o;
      }
      return best == nullptr ? std::string("none")
                             : fmt(best->fitness / best->limit, 3) + "x (" + best->pair + ", " + best->search +
                                   ", inlier share " + fmt(best->inlier_share) + ")";
    };
    md << "\nClosest refusal by fitness (fitness / its limit, validate.max_fitness x the coarser resolution): "
       << closest(false) << "; among the refusals whose inlier share passes the free-space test (>= "
       << fmt(base.validate.min_inlier_share) << "): " << closest(true) << ".\n";
    md << "\n## Cases\n\n| pair | search | accepted | fitness [m] | overlap | inlier share | t [s] | reason |\n"
          "|---|---|---|---|---|---|---|---|\n";
    for (const Outcome& o : outcomes) {
      md << "| " << o.pair << " | " << o.search << " | " << (o.wrong ? "**WRONG**" : o.accepted ? "where it belongs" : "no")
         << " | "
         << fmt(o.fitness, 4) << " | " << fmt(o.overlap) << " | " << fmt(o.inlier_share) << " | " << fmt(o.seconds, 2)
         << " | " << o.reason << " |\n";
    }
    std::cout << md.str();
    if (!out_path.empty()) std::ofstream(out_path) << md.str();
  } catch (const std::exception& e) {
    std::cerr << "mapmerge_bench_strangers: " << e.what() << "\n";
    return 1;
  }
  return 0;
}
