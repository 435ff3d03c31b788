// Bench of core/graph (issue 8): global pose error of spanning-tree chaining versus the
// optimised pose graph for 4, 8 and 16 robots on the real fr_079 map (fleet_sim.hpp), with and
// without one wrong edge, and the cost of one optimisation for 16 robots (cold and warm).
//
//   bench_graph [--trials N] [--timing-runs N] [--timing-only 1] [--real 1]
// --real 1 adds fleets cut from geb079 whose edges are real alignments (core/align).
// Prints Markdown (the tables of bench/results/graph.md).
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <random>
#include <string>
#include <vector>

#include "fleet_sim.hpp"
#include "mapmerge/align/align.hpp"
#include "mapmerge/map/crop.hpp"
#include "mapmerge/graph/pose_graph.hpp"
#include "mapmerge/map/map_io.hpp"

namespace mg = mapmerge::graph;
namespace sim = mapmerge::graph::sim;

namespace {

struct Options {
  int trials = 50;       // seeded fleets per robot count
  int timing_runs = 200;  // optimisations timed for 16 robots
  bool timing_only = false;
  bool real = false;      // also the fleets on real alignments (geb079; minutes of CPU)
};

Options parse(int argc, char** argv) {
  Options o;
  for (int i = 1; i + 1 < argc; i += 2) {
    const std::string a = argv[i];
    if (a == "--trials") o.trials = std::atoi(argv[i + 1]);
    else if (a == "--timing-runs") o.timing_runs = std::atoi(argv[i + 1]);
    else if (a == "--timing-only") o.timing_only = std::atoi(argv[i + 1]) != 0;
    else if (a == "--real") o.real = std::atoi(argv[i + 1]) != 0;
  }
  return o;
}

struct Errors {
  std::vector<double> mean_t, max_t, mean_r, max_r;  // per trial [m], [deg]
  void add(const mg::GraphSolution& s, const sim::Fleet& f, int reference) {
    double st = 0.0, mt = 0.0, sr = 0.0, mr = 0.0;
    int n = 0;
    for (std::size_t i = 0; i < f.ids.size(); ++i) {
      if (static_cast<int>(i) == reference) continue;
      const mg::RobotSolution* r = s.robot(f.ids[i]);
      if (!r->connected) continue;
      const sim::PoseError e = sim::pose_error(r->T_global_robot, f.truth(reference, static_cast<int>(i)));
      st += e.translation;
      sr += e.rotation_deg;
      mt = std::max(mt, e.translation);
      mr = std::max(mr, e.rotation_deg);
      ++n;
    }
    mean_t.push_back(n ? st / n : 0.0);
    mean_r.push_back(n ? sr / n : 0.0);
    max_t.push_back(mt);
    max_r.push_back(mr);
  }
};

/// CPU time of this thread [ms]: the machine is shared, wall time includes waiting.
double thread_cpu_ms() {
  timespec ts{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return static_cast<double>(ts.tv_sec) * 1e3 + static_cast<double>(ts.tv_nsec) * 1e-6;
}

double mean(const std::vector<double>& v) {
  double s = 0.0;
  for (double x : v) s += x;
  return v.empty() ? 0.0 : s / static_cast<double>(v.size());
}
double maximum(const std::vector<double>& v) { return v.empty() ? 0.0 : *std::max_element(v.begin(), v.end()); }
double percentile(std::vector<double> v, double p) {
  if (v.empty()) return 0.0;
  std::sort(v.begin(), v.end());
  return v[static_cast<std::size_t>(p * static_cast<double>(v.size() - 1) + 0.5)];
}

sim::FleetConfig fleet_config(int robots, unsigned seed) {
  sim::FleetConfig c;
  c.robots = robots;
  c.region_length = 14.0;  // every robot maps 14 m of the corridor: long chains for 4 robots
  c.seed = seed;
  return c;
}

void accuracy(const Options& o) {
  std::printf("## Accuracy (reference = robot00 at one end of the corridor; %d seeded fleets per row)\n\n", o.trials);
  std::printf("Errors of T_global_robot against truth over the non-reference robots: per fleet the mean and the max,\n"
              "then averaged (mean) or maximised (max) over the fleets.\n\n");
  std::printf("| robots | edges (mean) | chain mean [m] | graph mean [m] | chain max [m] | graph max [m] | "
              "chain mean [deg] | graph mean [deg] | chain max [deg] | graph max [deg] | graph <= chain (fleets) |\n");
  std::printf("|---|---|---|---|---|---|---|---|---|---|---|\n");
  for (int robots : {4, 8, 16}) {
    Errors chain, graph;
    double edges = 0.0;
    int better = 0;
    for (int t = 0; t < o.trials; ++t) {
      const sim::Fleet f = sim::make_fleet(sim::world(MAPMERGE_DATA_DIR "/fr_079.bt"),
                                           fleet_config(robots, 1000u + static_cast<unsigned>(t)));
      mg::PoseGraph g;
      sim::load(g, f, 0);
      chain.add(g.chain({}), f, 0);
      graph.add(g.optimise({}), f, 0);
      edges += static_cast<double>(f.edges.size());
      better += graph.mean_t.back() <= chain.mean_t.back() + 1e-9 ? 1 : 0;
    }
    std::printf("| %d | %.1f | %.3f | %.3f | %.3f | %.3f | %.2f | %.2f | %.2f | %.2f | %d / %d |\n", robots,
                edges / o.trials, mean(chain.mean_t), mean(graph.mean_t), maximum(chain.max_t),
                maximum(graph.max_t), mean(chain.mean_r), mean(graph.mean_r), maximum(chain.max_r),
                maximum(graph.max_r), better, o.trials);
  }
  std::printf("\n");
}

void wrong_edges(const Options& o, int wrong) {
  std::printf("## %d wrong edge%s (random edges turned 90..180 deg about z at their pivots)\n\n", wrong,
              wrong > 1 ? "s" : "");
  std::printf("A wrong pose is one off by more than 5 deg or 1 m (a wrong match is off by tens of degrees or metres).\n\n");
  std::printf("| robots | wrong edges rejected | correct edges rejected (total) | robots left unknown (total) | "
              "robots with a wrong pose (total) | robots unverified (total) | graph mean [m] | graph max [m] |\n");
  std::printf("|---|---|---|---|---|---|---|---|\n");
  for (int robots : {4, 8, 16}) {
    int caught = 0, false_rejections = 0, lost = 0, wrong_poses = 0, unverified = 0, robots_total = 0;
    Errors graph;
    for (int t = 0; t < o.trials; ++t) {
      sim::Fleet f = sim::make_fleet(sim::world(MAPMERGE_DATA_DIR "/fr_079.bt"),
                                     fleet_config(robots, 2000u + static_cast<unsigned>(t)));
      std::mt19937 rng(static_cast<unsigned>(t));
      std::vector<std::size_t> order(f.edges.size());
      for (std::size_t k = 0; k < order.size(); ++k) order[k] = k;
      std::shuffle(order.begin(), order.end(), rng);
      std::vector<std::string> wrong_ids;
      for (int w = 0; w < wrong && w < static_cast<int>(order.size()); ++w) {
        const std::size_t k = order[static_cast<std::size_t>(w)];
        sim::make_wrong(f, k, std::uniform_real_distribution<double>(90.0, 180.0)(rng));
        wrong_ids.push_back(mg::default_edge_id(f.edges[k].edge.source, f.edges[k].edge.target));
      }
      mg::PoseGraph g;
      sim::load(g, f, 0);
      const mg::GraphSolution s = g.optimise({});
      for (const auto& e : s.edges) {
        const bool is_wrong = std::find(wrong_ids.begin(), wrong_ids.end(), e.id) != wrong_ids.end();
        const bool rejected = e.state == mg::EdgeState::kRejected;
        caught += is_wrong && rejected ? 1 : 0;
        false_rejections += !is_wrong && rejected ? 1 : 0;
      }
      for (std::size_t i = 1; i < f.ids.size(); ++i) {
        const mg::RobotSolution* r = s.robot(f.ids[i]);
        ++robots_total;
        if (!r->connected) {
          ++lost;
          continue;
        }
        unverified += r->verified ? 0 : 1;
        const sim::PoseError e = sim::pose_error(r->T_global_robot, f.truth(0, static_cast<int>(i)));
        wrong_poses += (e.rotation_deg > 5.0 || e.translation > 1.0) ? 1 : 0;
      }
      graph.add(s, f, 0);
    }
    std::printf("| %d | %d / %d | %d | %d / %d | %d / %d | %d / %d | %.3f | %.3f |\n", robots, caught,
                wrong * o.trials, false_rejections, lost, robots_total, wrong_poses, robots_total, unverified,
                robots_total, mean(graph.mean_t), maximum(graph.max_t));
  }
  std::printf("\n");
}

void timing(const Options& o) {
  using Clock = std::chrono::steady_clock;
  std::vector<double> cold_cpu, warm_cpu;
  std::vector<double> cold, warm, consistency, solve, covariance, warm_iterations, cold_iterations;
  const int fleets = 10;
  double edges = 0.0;
  for (int t = 0; t < o.timing_runs; ++t) {
    const sim::Fleet f = sim::make_fleet(sim::world(MAPMERGE_DATA_DIR "/fr_079.bt"),
                                         fleet_config(16, 3000u + static_cast<unsigned>(t % fleets)));
    mg::PoseGraph g;
    sim::load(g, f, 0);
    auto t0 = Clock::now();
    double c0 = thread_cpu_ms();
    const mg::GraphSolution s = g.optimise({});
    cold_cpu.push_back(thread_cpu_ms() - c0);
    cold.push_back(std::chrono::duration<double, std::milli>(Clock::now() - t0).count());
    consistency.push_back(s.summary.consistency_ms);
    solve.push_back(s.summary.solve_ms);
    covariance.push_back(s.summary.covariance_ms);
    cold_iterations.push_back(s.summary.iterations);
    edges += static_cast<double>(f.edges.size());
    // Incremental: one edge re-aligned (its transform moves by 2 cm), warm start.
    mg::Edge e = f.edges[static_cast<std::size_t>(t) % f.edges.size()].edge;
    e.T_target_source.translation() += Eigen::Vector3d(0.02, -0.01, 0.0);
    g.add_or_update_edge(e);
    t0 = Clock::now();
    c0 = thread_cpu_ms();
    const mg::GraphSolution w = g.optimise({});
    warm_cpu.push_back(thread_cpu_ms() - c0);
    warm.push_back(std::chrono::duration<double, std::milli>(Clock::now() - t0).count());
    warm_iterations.push_back(w.summary.iterations);
  }
  std::printf("## Cost of one optimisation, 16 robots (%d runs over %d fleets, %.1f edges on average)\n\n",
              o.timing_runs, fleets, edges / o.timing_runs);
  std::printf("| | median [ms] | p95 [ms] | max [ms] |\n|---|---|---|---|\n");
  auto row = [](const char* name, const std::vector<double>& v) {
    std::printf("| %s | %.2f | %.2f | %.2f |\n", name, percentile(v, 0.5), percentile(v, 0.95), maximum(v));
  };
  row("cold optimise(), CPU time", cold_cpu);
  row("cold optimise(), wall time", cold);
  row("  cold, of which (wall) cycle checks", consistency);
  row("  cold, of which (wall) Ceres solve(s)", solve);
  row("  cold, of which (wall) covariances", covariance);
  row("warm optimise() after one edge changed, CPU time", warm_cpu);
  row("warm optimise() after one edge changed, wall time", warm);
  std::printf("\nLevenberg-Marquardt iterations: cold median %.0f, warm median %.0f.\n\n",
              percentile(cold_iterations, 0.5), percentile(warm_iterations, 0.5));
}

// ---- real alignments -----------------------------------------------------------------------

struct RealFleet {
  std::vector<std::string> ids;
  std::vector<Eigen::Isometry3d> T_robot_world;
  int global_edges = 0, refined_edges = 0, failed_pairs = 0, wrong_edges = 0;
  std::vector<std::string> wrong_ids;
  Eigen::Isometry3d truth(int a, int b) const { return T_robot_world[a] * T_robot_world[b].inverse(); }
};

Eigen::AlignedBox3d box_of(const octomap::OcTree& t) {
  double x0, y0, z0, x1, y1, z1;
  t.getMetricMin(x0, y0, z0);
  t.getMetricMax(x1, y1, z1);
  return Eigen::AlignedBox3d(Eigen::Vector3d(x0, y0, z0), Eigen::Vector3d(x1, y1, z1));
}

/// N robots along geb079 (x from -8 to 31 m), each mapping `length` m of the corridor in a random
/// frame; every pair sharing at least `min_shared` m of corridor is aligned: global search (no
/// guess), and where it fails, local refinement from the truth displaced by 0.3 m / 3 deg (what
/// the server does for an extra pair from its pose estimates). Edges go into `g` as aligned.
RealFleet real_fleet(const octomap::OcTree& world, int n, double length, double min_shared, unsigned seed,
                     mg::PoseGraph& g) {
  namespace ma = mapmerge::align;
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> uni(-1.0, 1.0);
  const double x0 = -8.0, x1 = 31.0;
  const double step = n > 1 ? (x1 - x0 - length) / (n - 1) : 0.0;
  RealFleet f;
  std::vector<ma::PreparedMap> prepared;
  std::vector<std::shared_ptr<const octomap::OcTree>> maps;
  const ma::AlignConfig config;
  for (int i = 0; i < n; ++i) {
    f.ids.push_back(sim::robot_name(i));
    const Eigen::Matrix4d T = mapmerge::paper_transform(3 * uni(rng), 3 * uni(rng), 0.2 * uni(rng), 2 * uni(rng),
                                                 2 * uni(rng), 180 * uni(rng));
    f.T_robot_world.emplace_back(T);
    const Eigen::AlignedBox3d box(Eigen::Vector3d(x0 + i * step, -8, -1), Eigen::Vector3d(x0 + i * step + length, 8, 4));
    maps.push_back(mapmerge::crop_and_transform(world, box, Eigen::Isometry3d(T)));
    prepared.push_back(ma::prepare_map(*maps.back(), config));
  }
  g.set_reference(f.ids[0]);
  for (const auto& id : f.ids) g.add_robot(id);
  for (int t = 0; t < n; ++t) {
    for (int s = t + 1; s < n; ++s) {
      if (length - (s - t) * step < min_shared) continue;
      ma::AlignResult r = ma::align(prepared[t], prepared[s], config);
      const bool global = r.accepted;
      if (!r.accepted) {
        const Eigen::Matrix4d guess = f.truth(t, s).matrix() * mapmerge::paper_transform(0.3, -0.3, 0.2, 1, -1, 3);
        r = ma::refine(prepared[t], prepared[s], guess, config);
      }
      if (!r.accepted) {
        ++f.failed_pairs;
        continue;
      }
      (global ? f.global_edges : f.refined_edges)++;
      const Eigen::Isometry3d T(r.T_target_source);
      const mg::AlignmentQuality q{r.inliers, r.fitness, r.overlap,
                                   mg::overlap_pivot(box_of(*maps[s]), box_of(*maps[t]), T)};
      const mg::EdgeInformation info = mg::information_from_alignment(q);
      if (!info.valid) continue;
      const sim::PoseError e = sim::pose_error(T, f.truth(t, s));
      if (e.rotation_deg > 5.0 || e.translation > 1.0) {
        ++f.wrong_edges;
        f.wrong_ids.push_back(mg::default_edge_id(f.ids[s], f.ids[t]));
      }
      g.add_or_update_edge({f.ids[s], f.ids[t], T, info.information, ""});
    }
  }
  return f;
}

void real_accuracy() {
  const auto world = mapmerge::read_octree_file(MAPMERGE_DATA_DIR "/geb079.bt");
  std::printf("## Real alignments (geb079, one seeded fleet per row, reference robot00 at one end)\n\n");
  std::printf("Robots map 14 m strips of the corridor, evenly spaced, each in a random frame; every pair sharing\n"
              "at least 4 m is aligned by core/align (global search; where it fails, refinement from the truth\n"
              "displaced by 0.3 m / 3 deg, as the server's extra pairs refine from pose estimates). A wrong edge\n"
              "is one off the truth by more than 5 deg or 1 m. Errors over the non-reference robots.\n\n");
  std::printf("| robots | edges (global + refined) | pairs not aligned | wrong edges (rejected) | chain mean [m] | "
              "graph mean [m] | chain max [m] | graph max [m] | chain max [deg] | graph max [deg] | "
              "robots placed (graph) |\n|---|---|---|---|---|---|---|---|---|---|---|\n");
  for (int n : {4, 8, 16}) {
    mg::PoseGraph g;
    const RealFleet f = real_fleet(*world, n, 14.0, 4.0, 77u + static_cast<unsigned>(n), g);
    const mg::GraphSolution chained = g.chain({});
    const mg::GraphSolution optimised = g.optimise({});
    int rejected = 0;
    for (const auto& id : f.wrong_ids) rejected += optimised.edge(id)->state == mg::EdgeState::kRejected ? 1 : 0;
    const auto errors = [&](const mg::GraphSolution& s, double& mean_t, double& max_t, double& max_r) {
      int k = 0;
      mean_t = max_t = max_r = 0.0;
      for (int i = 1; i < n; ++i) {
        const mg::RobotSolution* r = s.robot(f.ids[i]);
        if (!r->connected) continue;
        const sim::PoseError e = sim::pose_error(r->T_global_robot, f.truth(0, i));
        mean_t += e.translation;
        max_t = std::max(max_t, e.translation);
        max_r = std::max(max_r, e.rotation_deg);
        ++k;
      }
      mean_t = k ? mean_t / k : 0.0;
      return k;
    };
    double cm, cx, cr, gm, gx, gr;
    errors(chained, cm, cx, cr);
    const int placed = errors(optimised, gm, gx, gr);
    std::printf("| %d | %d (%d + %d) | %d | %d (%d) | %.3f | %.3f | %.3f | %.3f | %.2f | %.2f | %d / %d |\n", n,
                f.global_edges + f.refined_edges, f.global_edges, f.refined_edges, f.failed_pairs, f.wrong_edges,
                rejected, cm, gm, cx, gx, cr, gr, placed, n - 1);
    std::fflush(stdout);
  }
  std::printf("\n");
}

}  // namespace

int main(int argc, char** argv) {
  const Options o = parse(argc, argv);
  if (!o.timing_only) {
    accuracy(o);
    wrong_edges(o, 1);
    wrong_edges(o, 2);
  }
  timing(o);
  if (o.real) real_accuracy();
  return 0;
}
