// Accuracy/speed bench of mapmerge::align (issue 3). Cuts a real map into two parts with a
// chosen overlap (share of the map's occupied voxels), moves one by a known transform T_R,
// aligns, and prints the paper's Table 1 columns plus rotation/translation error, accepted,
// success (RE < 5 deg and TE < 0.3 m) and wrong merges (accepted but not a success).
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <iostream>
#include <map>
#include <random>
#include <sstream>

#include <CLI/CLI.hpp>
#include <Eigen/Geometry>

#include "bench_common.hpp"
#include "mapmerge/align/align.hpp"
#include "mapmerge/map/crop.hpp"
#include "mapmerge/map/held_map.hpp"
#include "mapmerge/map/map_codec.hpp"
#include "mapmerge/map/map_io.hpp"

namespace ma = mapmerge::align;
using mapmerge::bench::Errors;
using mapmerge::bench::errors;
using mapmerge::bench::fmt;
using Clock = std::chrono::steady_clock;

namespace {

double ms_since(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

struct Pose {  ///< T_R in the paper's format
  double x, y, z, roll, pitch, yaw;
  Eigen::Matrix4d matrix() const { return mapmerge::paper_transform(x, y, z, roll, pitch, yaw); }
  std::string str() const {
    char b[96];
    std::snprintf(b, sizeof b, "(%.1f, %.1f, %.1f, %.0f°, %.0f°, %.0f°)", x, y, z, roll, pitch, yaw);
    return b;
  }
};

struct Variant {
  std::string name;
  ma::AlignConfig config;
};

struct Row {
  std::string map, variant, pose;
  std::size_t n1 = 0, n2 = 0;
  double overlap = 0, fitness = 0, t_err = 0, rot_err = 0, trans_err = 0, time_ms = 0;
  bool accepted = false, success = false;
  bool rescued = false;  ///< a second search on denser features ran (AlignConfig::rescue)
  std::string reason;
  double inlier_share = 0, overlap_est = 0;
  std::size_t inliers = 0;
  /// T_err of the local alignment (stage 8) started at the true transform: the error the data
  /// itself leaves (the source was resampled on its own grid after the move), a floor for T_err.
  double floor_t_err = std::nan("");
  double floor_fitness = std::nan("");  ///< the fitness (Eq. 6) of that transform [m]
};

std::vector<Variant> make_variants(const ma::AlignConfig& base, bool all) {
  std::vector<Variant> v{{"default", base}};
  if (!all) return v;
  for (auto [mname, method] : {std::pair{"SAC", ma::MatchMethod::kRansac}, std::pair{"GCC", ma::MatchMethod::kGcc}})
    for (auto [rname, refine] : {std::pair{"ICP", ma::RefineMethod::kIcp}, std::pair{"OICP", ma::RefineMethod::kOicp},
                                 std::pair{"NDT", ma::RefineMethod::kNdt}})
      for (bool div : {true, false}) {
        ma::AlignConfig c = base;
        c.match.method = method;
        c.refine.method = refine;
        c.submodels.enabled = div;
        v.push_back({std::string(mname) + "+" + rname + (div ? "_DIV" : ""), c});
      }
  ma::AlignConfig c = base;
  c.match.iterations = 5000;  // PCL's loops score every sample on the keypoint clouds: slower
  c.match.method = ma::MatchMethod::kSacIa;
  v.push_back({"SAC-IA(PCL)+OICP", c});
  c.match.method = ma::MatchMethod::kPrerejective;
  v.push_back({"PREREJ(PCL)+OICP", c});
  c = base;
  c.describe.method = ma::Descriptor::kShot;
  v.push_back({"SHOT+SAC+OICP", c});
  return v;
}

/// Preparation depends only on stages 1-5: share it between variants with equal settings.
std::string prep_key(const ma::AlignConfig& c) {
  return std::string(ma::to_string(c.describe.method)) + std::to_string(c.preprocess.voxel_size) +
         std::to_string(c.describe.radius) + std::to_string(c.keypoints.salient_radius);
}

struct Prepared {
  ma::PreparedMap map;
  double ms = 0;
};

Prepared prepare(const octomap::OcTree& tree, const ma::AlignConfig& c) {
  const auto t0 = Clock::now();
  Prepared p{ma::prepare_map(tree, c), 0};
  p.ms = ms_since(t0);
  return p;
}

/// Where an estimate's error lies: its turn as a rotation vector in the target frame [deg] and
/// how far (and which way) it moves the point `at` of the target frame [m]. T_err measures the
/// error at the frame's origin, which a small turn moves far when the overlap lies far from it.
std::string error_at(const Eigen::Matrix4d& T_est_target_source, const Eigen::Matrix4d& T_R, const Eigen::Vector3d& at) {
  const Eigen::Isometry3d E(T_est_target_source * T_R);  // target -> target; identity when exact
  const Eigen::AngleAxisd turn(E.linear());
  const Eigen::Vector3d deg = turn.axis() * turn.angle() * 180.0 / M_PI;
  const Eigen::Vector3d moved = E * at - at;
  char b[200];
  std::snprintf(b, sizeof b, "turn (%.2f, %.2f, %.2f) deg, moves the overlap's centre %.3f m (%.2f, %.2f, %.2f)",
                deg.x(), deg.y(), deg.z(), moved.norm(), moved.x(), moved.y(), moved.z());
  return b;
}

Row run_case(const std::string& map, const Prepared& target, const Prepared& source,
             const Variant& v, const Pose& pose, double overlap, bool floor_only = false,
             const Eigen::Vector3d& overlap_centre = Eigen::Vector3d::Zero()) {
  const auto t0 = Clock::now();
  ma::AlignResult r;
  if (!floor_only) r = ma::align(target.map, source.map, v.config);
  const double align_ms = ms_since(t0);
  Row row;
  row.map = map;
  row.variant = v.name;
  row.pose = pose.str();
  row.n1 = target.map.num_points();
  row.n2 = source.map.num_points();
  row.overlap = overlap;
  row.accepted = r.accepted;
  row.fitness = r.fitness;
  row.reason = r.reason;
  row.rescued = r.rescued;
  row.inlier_share = r.inlier_share;
  row.overlap_est = r.overlap;
  row.inliers = r.inliers;
  // Two preparations run in parallel in `mapmerge merge`: count the slower one.
  row.time_ms = std::max(target.ms, source.ms) + align_ms;
  if (v.name == "default") {
    const ma::AlignResult from_truth = ma::refine(target.map, source.map, pose.matrix().inverse(), v.config);
    const Errors floor = errors(from_truth.T_target_source, pose.matrix());
    row.floor_t_err = floor.t_err;
    row.floor_fitness = from_truth.fitness;
    if (floor_only)
      std::cerr << std::lround(overlap * 100) << "% " << pose.str() << " from the truth: T_err " << fmt(floor.t_err)
                << " rot " << fmt(floor.rot_deg, 2) << " trans " << fmt(floor.trans_m) << " fitness "
                << fmt(from_truth.fitness, 4) << (from_truth.accepted ? "" : " (refused: " + from_truth.reason + ")") << "; "
                << error_at(from_truth.T_target_source, pose.matrix(), overlap_centre) << "\n";
  }
  if (r.accepted) {
    const Errors e = errors(r.T_target_source, pose.matrix());
    row.t_err = e.t_err;
    row.rot_err = e.rot_deg;
    row.trans_err = e.trans_m;
    row.success = e.success();
  }
  return row;
}

double quantile(std::vector<double> v, double q) {
  if (v.empty()) return std::nan("");
  std::sort(v.begin(), v.end());
  const auto i = static_cast<std::size_t>(std::min<double>(v.size() - 1, q * (v.size() - 1) + 0.5));
  return v[i];
}

void print_rows(std::ostream& out, const std::vector<Row>& rows) {
  out << "| map | variant | n1 | n2 | T_R (x,y,z,R,P,Y) | r | f_s [m] | T_err | rot err [deg] | trans err [m] | accepted | success | t [s] | T_err, ICP from the truth |\n"
      << "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n";
  for (const Row& r : rows) {
    out << "| " << r.map << " | " << r.variant << " | " << r.n1 / 1000 << "k | " << r.n2 / 1000 << "k | "
        << r.pose << " | " << fmt(r.overlap * 100, 0) << "% | "
        << (r.accepted ? fmt(r.fitness, 4) : "-") << " | " << (r.accepted ? fmt(r.t_err) : "-") << " | "
        << (r.accepted ? fmt(r.rot_err, 2) : "-") << " | " << (r.accepted ? fmt(r.trans_err) : "-")
        << " | " << (r.accepted ? "yes" : "no") << " | "
        << (r.success ? "yes" : (r.accepted ? "**WRONG**" : "no")) << " | " << fmt(r.time_ms / 1000.0, 2)
        << " | " << fmt(r.floor_t_err) << " |\n";
  }
}

void print_summary(std::ostream& out, const std::vector<Row>& rows) {
  std::map<std::pair<std::string, int>, std::vector<const Row*>> groups;
  std::vector<std::string> order;
  for (const Row& r : rows) {
    if (std::find(order.begin(), order.end(), r.variant) == order.end()) order.push_back(r.variant);
    groups[{r.variant, static_cast<int>(std::lround(r.overlap * 100))}].push_back(&r);
  }
  out << "| variant | r | cases | success | accepted | wrong merges | median T_err | p95 T_err | median rot [deg] | median trans [m] | median t [s] | median T_err, ICP from the truth |\n"
      << "|---|---|---|---|---|---|---|---|---|---|---|---|\n";
  for (const std::string& name : order)
    for (const auto& [key, list] : groups) {
      if (key.first != name) continue;
      std::vector<double> terr, rot, trans, time, floor;
      std::size_t ok = 0, acc = 0, wrong = 0;
      for (const Row* r : list) {
        ok += r->success;
        acc += r->accepted;
        wrong += r->accepted && !r->success;
        if (r->success) {
          terr.push_back(r->t_err);
          rot.push_back(r->rot_err);
          trans.push_back(r->trans_err);
        }
        time.push_back(r->time_ms / 1000.0);
        if (!std::isnan(r->floor_t_err)) floor.push_back(r->floor_t_err);
      }
      const double n = static_cast<double>(list.size());
      out << "| " << name << " | " << key.second << "% | " << list.size() << " | " << fmt(100.0 * ok / n, 0)
          << "% | " << fmt(100.0 * acc / n, 0) << "% | " << wrong << " | " << fmt(quantile(terr, 0.5))
          << " | " << fmt(quantile(terr, 0.95)) << " | " << fmt(quantile(rot, 0.5), 2) << " | "
          << fmt(quantile(trans, 0.5)) << " | " << fmt(quantile(time, 0.5), 2) << " | "
          << fmt(quantile(floor, 0.5)) << " |\n";
    }
}

}  // namespace

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v.empty() ? 0.0 : v[v.size() / 2];
}

/// The server's preparation of a received map (its `.bt` bytes, held undecoded): read off the
/// bytes, against building the octree first and preparing that (the way before). Median ms.
void prepare_timing(const octomap::OcTree& tree, const ma::AlignConfig& config, int runs) {
  const auto bytes = mapmerge::encode_map(tree, mapmerge::Encoding::kOctomapBt);
  const auto held = mapmerge::check_map(bytes.data(), bytes.size(), mapmerge::Encoding::kOctomapBt, {}).map;
  if (!held) throw std::runtime_error("the map's bytes did not check");
  std::printf("map: %zu nodes, %.3f m, %zu KiB as .bt; %d runs, median [ms]\n\n", held->num_nodes(),
              held->resolution(), bytes.size() / 1024, runs);
  std::printf("| preparation | off the bytes | tree build | + prepare the tree | = via the tree |\n|---|---|---|---|---|\n");
  for (const bool features : {false, true}) {
    std::vector<double> body, build, from_tree;
    for (int i = 0; i < runs; ++i) {
      auto t0 = Clock::now();
      { const auto p = features ? ma::prepare_map(*held, config) : ma::prepare_for_refine(*held, config); }
      body.push_back(ms_since(t0));
      t0 = Clock::now();
      const auto built = held->tree();
      build.push_back(ms_since(t0));
      t0 = Clock::now();
      { const auto p = features ? ma::prepare_map(*built, config) : ma::prepare_for_refine(*built, config); }
      from_tree.push_back(ms_since(t0));
      held->release_tree();
    }
    std::printf("| %s | %.0f | %.0f | %.0f | %.0f |\n", features ? "prepare_map" : "prepare_for_refine", median(body),
                median(build), median(from_tree), median(build) + median(from_tree));
  }
}

int main(int argc, char** argv) {
  CLI::App app{"mapmerge_bench_align: alignment accuracy and speed on real maps"};
  std::string map_path = std::string(MAPMERGE_DATA_DIR) + "/fr_079.bt";
  std::string config_path, out_path, write_pair;
  std::vector<int> overlaps{10, 15, 20, 30, 40};
  int trials = 12, variant_trials = 2, coarsen = 1, axis = 0;
  unsigned seed = 1;
  bool quick = false, all_variants = false, paper_pair = false, floor_only = false;
  int prepare_runs = 0;
  double max_translation = 10.0, max_tilt = 5.0;
  double z_min = -1e9, z_max = 1e9;
  app.add_option("--map", map_path, "real map (.bt/.ot)");
  app.add_option("--config", config_path, "YAML config of the default variant");
  app.add_option("--overlaps", overlaps, "overlaps [%]")->delimiter(',');
  app.add_option("--trials", trials, "random transforms per overlap (default variant)");
  app.add_option("--variant-trials", variant_trials, "of those, how many also run every variant");
  app.add_option("--coarsen", coarsen, "coarsen the map by this factor first (e.g. 4: 5 cm -> 20 cm)");
  bool coarsen_parts = false;
  app.add_flag("--coarsen-parts", coarsen_parts,
               "with --coarsen: cut and move each part at the map's own resolution, then coarsen it on its own "
               "grid (a robot mapping at the coarse resolution), instead of resampling the coarse map");
  double refine_to = 0.0;
  app.add_option("--refine", refine_to,
                 "resample both parts of each case (cut and moved at the map's resolution) onto this finer grid [m], "
                 "e.g. 0.02: the pipeline sees a 2 cm map with the map's own detail");
  std::string partner_path;
  app.add_option("--partner", partner_path,
                 "cut each case's source part from this map of the same place in the same frame (e.g. geb079.bt, "
                 "8 cm, for fr_079.bt, 5 cm: pairs of mixed resolutions from two datasets), not from --map");
  app.add_option("--axis", axis, "cut along x (0) or y (1)");
  app.add_option("--seed", seed, "random seed of the transforms");
  app.add_option("--max-translation", max_translation, "|x|,|y| of T_R up to this [m]");
  app.add_option("--max-tilt", max_tilt, "|roll|,|pitch| of T_R up to this [deg]");
  app.add_option("--zmin", z_min, "keep only the map's voxels above this z first [m]");
  app.add_option("--zmax", z_max, "keep only the map's voxels below this z first [m]");
  app.add_option("--out", out_path, "also write the Markdown report here");
  app.add_option("--write-pair", write_pair, "write the paper's pair as DIR/scene.bt and DIR/model.bt and exit");
  app.add_flag("--quick", quick, "two overlaps, three transforms, default variant");
  app.add_flag("--all-variants", all_variants, "SAC/GCC x ICP/OICP/NDT x DIV/plain and the PCL/SHOT variants");
  app.add_flag("--floor-only", floor_only, "only refine from the true transform (the accuracy floor), no global search");
  app.add_flag("--paper-pair", paper_pair, "also run the paper's own pair (fr_079 only)");
  app.add_option("--prepare-timing", prepare_runs,
                 "only time preparing the map from its .bt bytes (as the server does) against via its octree, N runs");
  CLI11_PARSE(app, argc, argv);
  if (quick) {
    overlaps = {15, 30};
    trials = 3;
    all_variants = false;
  }
  try {
    const ma::AlignConfig base = config_path.empty() ? ma::AlignConfig{} : ma::load_align_config(config_path);
    std::unique_ptr<octomap::OcTree> tree = mapmerge::read_octree_file(map_path);
    // With --coarsen-parts, `fine` is what the parts are cut from; `tree` (coarse) still sets the cut.
    std::unique_ptr<octomap::OcTree> fine;
    if (coarsen > 1 && coarsen_parts) fine = std::move(tree);
    if (coarsen > 1) tree = mapmerge::coarsen(fine ? *fine : *tree, coarsen);
    std::string name = map_path.substr(map_path.find_last_of('/') + 1);
    if (z_min > -1e8 || z_max < 1e8) {
      const Eigen::AlignedBox3d slab(Eigen::Vector3d(-1e6, -1e6, z_min), Eigen::Vector3d(1e6, 1e6, z_max));
      tree = mapmerge::crop_and_transform(*tree, slab, Eigen::Isometry3d::Identity());
      if (fine) fine = mapmerge::crop_and_transform(*fine, slab, Eigen::Isometry3d::Identity());
      name += " z " + fmt(z_min, 1) + ".." + fmt(z_max, 1) + " m";
    }
    if (coarsen > 1) name += " @" + fmt(tree->getResolution(), 2) + "m" + (fine ? " (parts)" : "");
    if (prepare_runs > 0) {
      std::printf("%s\n", name.c_str());
      prepare_timing(*tree, base, prepare_runs);
      return 0;
    }
    if (refine_to > 0.0) name += " on a " + fmt(refine_to, 3) + " m grid";
    std::unique_ptr<octomap::OcTree> partner;
    if (!partner_path.empty()) {
      partner = mapmerge::read_octree_file(partner_path);
      name += " <- " + partner_path.substr(partner_path.find_last_of('/') + 1);
    }
    const auto on_grid = [&](std::unique_ptr<octomap::OcTree> part) {
      if (fine) return mapmerge::coarsen(*part, coarsen);
      return refine_to > 0.0 ? mapmerge::refine(*part, refine_to) : std::move(part);
    };
    const octomap::OcTree& cut_from = fine ? *fine : *tree;
    const std::vector<Variant> variants = make_variants(base, all_variants);
    std::vector<Row> rows;
    std::mt19937 rng(seed);
    std::uniform_real_distribution<double> yaw(-180.0, 180.0), tilt(-max_tilt, max_tilt),
        shift(-max_translation, max_translation), lift(-0.5, 0.5);

    const Pose paper{12, 6, 0.5, 5, 5, 60};
    if (!write_pair.empty() || paper_pair) {
      const Eigen::AlignedBox3d scene_box(Eigen::Vector3d(-10, -10, 0), Eigen::Vector3d(2, 10, 2));
      const Eigen::AlignedBox3d model_box(Eigen::Vector3d(-2, -10, 0), Eigen::Vector3d(10, 10, 2));
      auto scene = mapmerge::crop_and_transform(*tree, scene_box, Eigen::Isometry3d::Identity());
      auto model = mapmerge::crop_and_transform(*tree, model_box, Eigen::Isometry3d(paper.matrix()));
      if (!write_pair.empty()) {
        mapmerge::write_octree_file(*scene, write_pair + "/scene.bt");
        mapmerge::write_octree_file(*model, write_pair + "/model.bt");
        std::cout << "wrote " << write_pair << "/scene.bt and model.bt\n";
        return 0;
      }
      const Eigen::AlignedBox3d both(Eigen::Vector3d(-2, -10, 0), Eigen::Vector3d(2, 10, 2));
      const Eigen::AlignedBox3d all(Eigen::Vector3d(-10, -10, 0), Eigen::Vector3d(10, 10, 2));
      const double r = double(mapmerge::count_occupied(*tree, both)) / double(mapmerge::count_occupied(*tree, all));
      std::map<std::string, std::pair<Prepared, Prepared>> cache;
      for (const Variant& v : variants) {
        auto& slot = cache[prep_key(v.config)];
        if (slot.first.map.empty()) slot = {prepare(*scene, v.config), prepare(*model, v.config)};
        rows.push_back(run_case("paper pair", slot.first, slot.second, v, paper, r));
        std::cerr << rows.back().variant << " paper pair: " << (rows.back().success ? "ok" : rows.back().reason) << "\n";
      }
    }

    for (int pct : overlaps) {
      const auto [target_box, source_box] = mapmerge::overlap_cut(*tree, axis, pct / 100.0);
      auto target = on_grid(mapmerge::crop_and_transform(cut_from, target_box, Eigen::Isometry3d::Identity()));
      const Eigen::Vector3d overlap_centre = target_box.intersection(source_box).center();
      std::map<std::string, Prepared> target_cache;
      for (int t = 0; t < trials; ++t) {
        const Pose pose{shift(rng), shift(rng), lift(rng), tilt(rng), tilt(rng), yaw(rng)};
        auto source = on_grid(
            mapmerge::crop_and_transform(partner ? *partner : cut_from, source_box, Eigen::Isometry3d(pose.matrix())));
        std::map<std::string, Prepared> source_cache;
        const std::size_t nv = t < variant_trials ? variants.size() : 1;
        for (std::size_t vi = 0; vi < nv; ++vi) {
          const Variant& v = variants[vi];
          const std::string key = prep_key(v.config);
          if (!target_cache.count(key)) target_cache[key] = prepare(*target, v.config);
          if (!source_cache.count(key)) source_cache[key] = prepare(*source, v.config);
          rows.push_back(run_case(name, target_cache[key], source_cache[key], v, pose, pct / 100.0, floor_only, overlap_centre));
          const Row& r = rows.back();
          if (floor_only) continue;  // run_case printed the floor
          std::cerr << pct << "% " << pose.str() << " " << v.name << ": "
                    << (r.success ? "ok" : (r.accepted ? "WRONG" : "rejected (" + r.reason + ")"))
                    << (r.rescued ? " [rescue]" : "")
                    << " rot " << fmt(r.rot_err, 2) << " trans " << fmt(r.trans_err) << " t "
                    << fmt(r.time_ms / 1000, 2) << "s f " << fmt(r.fitness, 4) << " share "
                    << fmt(r.inlier_share) << " ovl " << fmt(r.overlap_est) << " in " << r.inliers
                    << "; from the truth: T_err " << fmt(r.floor_t_err) << " f " << fmt(r.floor_fitness, 4) << "\n";
        }
      }
    }
    if (floor_only) {  // the floor per overlap, on stdout; no report
      std::cout << "| r | cases | median T_err, ICP from the truth | p95 | max |\n|---|---|---|---|---|\n";
      for (int pct : overlaps) {
        std::vector<double> f;
        for (const Row& r : rows)
          if (std::lround(r.overlap * 100) == pct) f.push_back(r.floor_t_err);
        std::cout << "| " << pct << "% | " << f.size() << " | " << fmt(quantile(f, 0.5)) << " | "
                  << fmt(quantile(f, 0.95)) << " | " << fmt(quantile(f, 1.0)) << " |\n";
      }
      return 0;
    }
    std::ostringstream md;
    md << "# Alignment bench: " << name << "\n\n"
       << "Generated by `mapmerge_bench_align` (bench/align). Each case cuts the map into a target part and a "
          "source part sharing r of the occupied voxels, moves the source by T_R (yaw uniform over the full "
          "circle, roll/pitch up to " << fmt(max_tilt, 0) << "°, |x|,|y| up to " << fmt(max_translation, 0)
       << " m) and aligns it. T_err = ||T_est·T_R^-1 − I||_F; success = rot err < 5° and trans err < 0.3 m; "
          "a wrong merge is an accepted result that is not a success. t = slower map preparation + align "
          "(the two preparations run in parallel in `mapmerge merge`; file I/O excluded). T_err and errors "
          "in the summary are over successful cases.";
    if (partner)
      md << " The source part is cut from `" << partner_path.substr(partner_path.find_last_of('/') + 1)
         << "` (the same place in the same frame, another dataset at " << fmt(partner->getResolution(), 2)
         << " m), inside the source box of the cut of the target's map: r is that cut's overlap.";
    if (refine_to > 0.0)
      md << " Both parts are cut and moved at the map's own resolution, then resampled onto the "
         << fmt(refine_to, 3) << " m grid (`mapmerge::refine`): the pipeline sees maps at that resolution "
            "whose detail is still the original map's.";
    if (fine)
      md << " Both parts are cut and moved at the map's own resolution (" << fmt(fine->getResolution(), 2)
         << " m), then each is coarsened on its own grid (`--coarsen-parts`): two maps of one place at "
         << fmt(tree->getResolution(), 2)
         << " m as two robots mapping at that resolution would hold them, neither a resampling of the other's "
            "voxels. Each wall then lies up to half a voxel off in each part, independently.";
    md << "\n\n## Summary\n\n";
    print_summary(md, rows);
    md << "\n## Cases\n\n";
    print_rows(md, rows);
    std::cout << md.str();
    if (!out_path.empty()) {
      std::ofstream f(out_path);
      f << md.str();
    }
  } catch (const std::exception& e) {
    std::cerr << "mapmerge_bench_align: " << e.what() << "\n";
    return 1;
  }
  return 0;
}
