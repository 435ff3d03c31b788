// Load bench of a real mapmerge-server on loopback: N robots (default 16) publish Freiburg-size
// maps (windows of fr_079, each growing and shrinking over a few variants, so every update is a
// new map) every second for --duration (default 10 min). Samples the server's RSS and queue,
// then stops the robots and waits until every robot's final map is fused. Prints updates
// received, merges run, merges coalesced, p50/p99 update-to-global latency (publish -> first
// global map holding that update or a newer one of the robot) and peak RSS, as Markdown.
#include <algorithm>
#include <cstdio>
#include <fstream>
#include <map>
#include <mutex>
#include <random>

#include <CLI/CLI.hpp>

#include "child_process.hpp"
#include "fleet.hpp"
#include "mapmerge/map/crop.hpp"
#include "mapmerge/map/map_codec.hpp"
#include "proc_stats.hpp"

namespace mt = mapmerge::test;
using Clock = std::chrono::steady_clock;

namespace {

struct Options {
  int robots = 16;            ///< fleet size
  double duration_s = 600;    ///< publishing time [s]
  double period_s = 1.0;      ///< each robot publishes this often [s]
  std::string map = "fr_079.bt";
  double window_share = 0.5;  ///< each robot's window: this share of the map's length
  int variants = 4;           ///< maps per robot, published in turn (each a change)
  double sample_s = 10;       ///< RSS / queue sampling period [s]
  double drain_s = 300;       ///< after the robots stop: waiting for every final map [s]
  double idle_s = 45;         ///< then the fleet stays silent this long before RSS is read again [s]
  int threads = 2;            ///< server merge threads
  int domain = 101;           ///< outside the CTest pool
};

double secs(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

/// Per robot, `variants` encoded maps: its window of the world, 85..100 % of its length, in
/// its own random frame (robot 1's frame is the world's).
std::vector<std::vector<std::vector<std::uint8_t>>> make_fleet(const Options& o, const octomap::OcTree& world,
                                                              double& mean_kb, double& mean_tree_mb) {
  double x0, y0, z0, x1, y1, z1;
  world.getMetricMin(x0, y0, z0);
  world.getMetricMax(x1, y1, z1);
  const double length = (x1 - x0) * o.window_share;
  const double step = o.robots > 1 ? ((x1 - x0) - length) / (o.robots - 1) : 0.0;
  std::mt19937 rng(16);
  std::uniform_real_distribution<double> yaw(-180, 180), off(-5, 5);
  std::vector<std::vector<std::vector<std::uint8_t>>> fleet;
  double bytes = 0, tree_bytes = 0;
  for (int i = 0; i < o.robots; ++i) {
    const Eigen::Isometry3d T = i == 0 ? Eigen::Isometry3d::Identity()
                                       : mapmerge::make_transform(off(rng), off(rng), 0, 0, 0, yaw(rng));
    fleet.emplace_back();
    for (int k = 0; k < o.variants; ++k) {
      const double len = length * (0.85 + 0.15 * k / std::max(1, o.variants - 1));
      const Eigen::AlignedBox3d box(Eigen::Vector3d(x0 + i * step, y0, z0), Eigen::Vector3d(x0 + i * step + len, y1, z1));
      const auto tree = mapmerge::crop_and_transform(world, box, T);
      fleet.back().push_back(mapmerge::encode_map(*tree, mapmerge::Encoding::kOctomapBt));
      bytes += static_cast<double>(fleet.back().back().size());
      tree_bytes += static_cast<double>(tree->memoryUsage());
    }
  }
  mean_kb = bytes / (o.robots * o.variants) / 1024.0;
  mean_tree_mb = tree_bytes / (o.robots * o.variants) / (1024.0 * 1024.0);
  return fleet;
}

/// Publish times of updates not yet seen in a global map, and the latencies of those seen.
class Latencies {
 public:
  void sent(const std::string& robot, std::uint64_t seq) {
    std::lock_guard<std::mutex> lock(mutex_);
    pending_[robot][seq] = Clock::now();
  }
  void global(const std::map<std::string, std::uint64_t>& contributors) {
    const auto now = Clock::now();
    std::lock_guard<std::mutex> lock(mutex_);
    for (const auto& [robot, seq] : contributors) {
      auto& p = pending_[robot];
      for (auto it = p.begin(); it != p.end() && it->first <= seq; it = p.erase(it)) {
        ms_.push_back(std::chrono::duration<double, std::milli>(now - it->second).count());
      }
    }
  }
  std::vector<double> sorted() const {
    std::lock_guard<std::mutex> lock(mutex_);
    auto v = ms_;
    std::sort(v.begin(), v.end());
    return v;
  }

 private:
  mutable std::mutex mutex_;
  std::map<std::string, std::map<std::uint64_t, Clock::time_point>> pending_;
  std::vector<double> ms_;
};

double percentile(const std::vector<double>& v, double p) {
  if (v.empty()) return -1;
  return v[std::min(v.size() - 1, static_cast<std::size_t>(p * static_cast<double>(v.size())))];
}

int aligned_count(const mt::FleetListener& op) {
  int n = 0;
  for (const auto& [id, p] : op.poses()) n += p.status == 1 ? 1 : 0;
  return n;
}

void print_sample(double t, const mapmerge::bench::ProcStats& p, const mt::ReceivedStatus& s, int aligned, int n) {
  std::printf("| %5.0f | %7.1f | %7.1f | %7.1f | %3d | %6lu | %6lu | %6lu | %3lu / %3lu | %2d/%2d |\n", t, p.rss_mb,
              p.hwm_mb, p.cpu_s, p.threads, static_cast<unsigned long>(s.updates_received),
              static_cast<unsigned long>(s.merges_run), static_cast<unsigned long>(s.merges_coalesced),
              static_cast<unsigned long>(s.merges_queued), static_cast<unsigned long>(s.merges_queued_max), aligned, n);
  std::fflush(stdout);
}

int run(const Options& o) {
  const auto world = mt::load_data_map(o.map);
  double mean_kb = 0, mean_tree_mb = 0;
  const auto maps = make_fleet(o, *world, mean_kb, mean_tree_mb);
  const std::string dir = mt::temp_dir("bench_load");
  std::ofstream(dir + "/load.yaml") << "merge: {threads: " << o.threads << "}\n";
  mt::ServerProcess server({"--domain", std::to_string(o.domain), "--profile", "local", "--state-dir", dir + "/state",
                            "--config", dir + "/load.yaml", "--reference", "r1"},
                           dir + "/server.log");
  mt::FleetListener op(o.domain);
  Latencies latencies;
  op.observe_globals([&](std::uint64_t, const std::map<std::string, std::uint64_t>& c) { latencies.global(c); }, false);
  std::vector<std::unique_ptr<mt::RobotPublisher>> pubs;
  std::vector<std::string> ids;
  for (int i = 0; i < o.robots; ++i) {
    ids.push_back("r" + std::to_string(i + 1));
    pubs.push_back(std::make_unique<mt::RobotPublisher>(o.domain, ids.back()));
  }
  std::printf("%d robots, map %s (%.0f KiB per update on average, %d variants each), one update per robot every "
              "%.1f s for %.0f s; server: %d merge threads, state in SQLite; log %s/server.log\n\n",
              o.robots, o.map.c_str(), mean_kb, o.variants, o.period_s, o.duration_s, o.threads, dir.c_str());
  std::printf("| t [s] | RSS [MiB] | peak [MiB] | CPU [s] | thr | received | merges | coalesced | queued / max | aligned |\n");
  std::printf("|---|---|---|---|---|---|---|---|---|---|\n");
  std::this_thread::sleep_for(std::chrono::seconds(1));  // discovery settles

  const auto t0 = Clock::now();
  auto next_sample = t0;
  std::vector<std::uint64_t> last(static_cast<std::size_t>(o.robots), 0);
  std::uint64_t published = 0;
  std::vector<double> rss;
  const auto slot = std::chrono::duration<double>(o.period_s / o.robots);
  for (std::uint64_t round = 1; secs(t0) < o.duration_s; ++round) {
    for (int i = 0; i < o.robots; ++i) {  // staggered over the period, as independent robots are
      const auto at = t0 + std::chrono::duration_cast<Clock::duration>(
                               std::chrono::duration<double>(o.period_s * static_cast<double>(round - 1)) + slot * i);
      std::this_thread::sleep_until(at);
      const auto& bytes = maps[static_cast<std::size_t>(i)][round % maps[static_cast<std::size_t>(i)].size()];
      latencies.sent(ids[static_cast<std::size_t>(i)], round);
      pubs[static_cast<std::size_t>(i)]->publish_bytes(bytes, ids[static_cast<std::size_t>(i)], "s1", round);
      last[static_cast<std::size_t>(i)] = round;
      ++published;
      if (Clock::now() >= next_sample) {
        const auto p = mapmerge::bench::proc_stats(server.pid());
        rss.push_back(p.rss_mb);
        print_sample(secs(t0), p, op.status(), aligned_count(op), o.robots);
        next_sample += std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(o.sample_s));
      }
    }
  }
  const double publish_s = secs(t0);
  // The robots stop; every robot's last map must reach the global map.
  const auto t_stop = Clock::now();
  const auto all_final = [&] {
    const auto g = op.global();
    for (int i = 0; i < o.robots; ++i) {
      auto it = g.contributor_sequence.find(ids[static_cast<std::size_t>(i)]);
      if (it == g.contributor_sequence.end() || it->second != last[static_cast<std::size_t>(i)]) return false;
    }
    return true;
  };
  const bool fused = op.wait_for(all_final, std::chrono::seconds(static_cast<int>(o.drain_s)));
  const double drain = secs(t_stop);
  const auto p = mapmerge::bench::proc_stats(server.pid());
  print_sample(secs(t0), p, op.status(), aligned_count(op), o.robots);
  const auto s = op.status();
  const auto g = op.global();
  int final_fused = 0;
  for (int i = 0; i < o.robots; ++i) {
    auto it = g.contributor_sequence.find(ids[static_cast<std::size_t>(i)]);
    final_fused += it != g.contributor_sequence.end() && it->second == last[static_cast<std::size_t>(i)] ? 1 : 0;
  }
  // A fleet that stopped mapping: what the server holds once its alignment data has gone idle.
  std::this_thread::sleep_for(std::chrono::duration<double>(o.idle_s));
  const auto idle = mapmerge::bench::proc_stats(server.pid());
  print_sample(secs(t0), idle, op.status(), aligned_count(op), o.robots);
  const auto lat = latencies.sorted();
  const auto quarter = [&](double q) { return rss.empty() ? 0.0 : rss[std::min(rss.size() - 1, static_cast<std::size_t>(q * rss.size()))]; };
  std::printf("\n| figure | value |\n|---|---|\n");
  std::printf("| updates published | %lu in %.0f s |\n", static_cast<unsigned long>(published), publish_s);
  std::printf("| updates received (server) | %lu |\n", static_cast<unsigned long>(s.updates_received));
  std::printf("| merges run | %lu |\n", static_cast<unsigned long>(s.merges_run));
  std::printf("| merges coalesced | %lu |\n", static_cast<unsigned long>(s.merges_coalesced));
  std::printf("| merge queue now / max | %lu / %lu robots |\n", static_cast<unsigned long>(s.merges_queued),
              static_cast<unsigned long>(s.merges_queued_max));
  std::printf("| update-to-global latency p50 / p99 / max | %.0f / %.0f / %.0f ms (%zu updates seen fused) |\n",
              percentile(lat, 0.5), percentile(lat, 0.99), lat.empty() ? -1.0 : lat.back(), lat.size());
  std::printf("| RSS at 25/50/75/100 %% of the run | %.0f / %.0f / %.0f / %.0f MiB |\n", quarter(0.25), quarter(0.5),
              quarter(0.75), quarter(0.999));
  std::printf("| peak RSS (VmHWM) while publishing and draining / overall | %.0f / %.0f MiB (%.0f / %.0f MiB per robot) |\n",
              p.hwm_mb, idle.hwm_mb, p.hwm_mb / o.robots, idle.hwm_mb / o.robots);
  std::printf("| RSS after %.0f s without updates | %.0f MiB (%.0f MiB per robot) |\n", o.idle_s, idle.rss_mb,
              idle.rss_mb / o.robots);
  std::printf("| a robot's map: payload / its OcTree in memory (memoryUsage) | %.0f KiB / %.1f MiB |\n", mean_kb,
              mean_tree_mb);
  std::printf("| server CPU | %.0f s (%.2f cores) |\n", p.cpu_s, p.cpu_s / secs(t0));
  std::printf("| robots aligned | %d / %d |\n", aligned_count(op), o.robots);
  std::printf("| final maps fused | %d / %d, %.1f s after the robots stopped%s |\n", final_fused, o.robots, drain,
              fused ? "" : " (timed out)");
  std::printf("| global map version | %lu |\n", static_cast<unsigned long>(g.version));
  std::fflush(stdout);
  server.kill(SIGTERM);
  return fused ? 0 : 1;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"mapmerge-server load bench: N robots publishing Freiburg-size maps every period (loopback)"};
  Options o;
  app.add_option("--robots", o.robots, "fleet size")->check(CLI::Range(2, 64));
  app.add_option("--duration", o.duration_s, "publishing time [s]")->check(CLI::PositiveNumber);
  app.add_option("--period", o.period_s, "each robot publishes this often [s]")->check(CLI::PositiveNumber);
  app.add_option("--map", o.map, "map in data/")->check(CLI::Validator(mt::data_map_problem, "FILE in data/"));
  app.add_option("--window-share", o.window_share, "share of the map's length each robot sees");
  app.add_option("--variants", o.variants, "maps per robot published in turn")->check(CLI::Range(1, 16));
  app.add_option("--sample", o.sample_s, "RSS sampling period [s]")->check(CLI::PositiveNumber);
  app.add_option("--drain", o.drain_s, "wait for the final maps after the robots stop [s]");
  app.add_option("--idle", o.idle_s, "silence after the drain before RSS is read again [s]")->check(CLI::NonNegativeNumber);
  app.add_option("--threads", o.threads, "server merge threads")->check(CLI::Range(1, 64));
  app.add_option("--domain", o.domain, "DDS domain")->check(CLI::Range(0, 101));
  CLI11_PARSE(app, argc, argv);
  return run(o);
}
