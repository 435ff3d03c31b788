// End-to-end bench of a real mapmerge-server on loopback: N robots with maps cut from one real
// map publish at once; an operator participant measures the time until the global map holds
// them (first alignment), then the latency of incremental updates of known robots (publish ->
// updated global map received). Prints server CPU time and peak RSS per robot.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <map>
#include <condition_variable>
#include <mutex>
#include <numeric>
#include <optional>
#include <random>
#include <sstream>

#include <CLI/CLI.hpp>

#include "child_process.hpp"
#include "fleet.hpp"
#include "mapmerge/client/client.hpp"
#include "mapmerge/map/crop.hpp"
#include "mapmerge/map/map_codec.hpp"
#include "proc_stats.hpp"

namespace mt = mapmerge::test;
using Clock = std::chrono::steady_clock;

namespace {

struct Options {
  std::vector<int> robots{2, 4, 8, 16};
  std::string map = "geb079.bt";
  int domain = 101;  // outside the CTest pool (1..100): benches never meet running tests
  int updates = 6;
  int timeout_s = 900;
  double strip_share = 0.45;  ///< each robot sees this share of the map's length
  double grow = 1.0;          ///< an incremental update grows a robot's map by this much [m]
  double period_s = 0.0;      ///< an update starts this long after the last one started (0: at once)
  std::string log_level = "info";  ///< the server's
  std::string receiver = "client";  ///< who receives the global map: "client" (mapmerge::Client) or "raw" (decodes each)
};

/// The fleet's side: a mapmerge::Client observer (patches each new version from its changed
/// blocks when it can), noting when its callback saw each robot's map sequence.
class ClientReceiver {
 public:
  explicit ClientReceiver(int domain) : client_(options(domain)) {
    client_.on_global_map([this](const std::shared_ptr<const mapmerge::client::GlobalMap>& g) {
      const auto now = Clock::now();
      std::lock_guard<std::mutex> lock(mutex_);
      for (const auto& c : g->contributors) seen_.emplace(std::make_pair(c.robot_id, c.sequence_number), now);
      cv_.notify_all();
    });  // the map is let go at once: the client may patch it in place
  }
  /// When the client's callback first held `robot` at `sequence`, if within `timeout`.
  std::optional<Clock::time_point> wait(const std::string& robot, std::uint64_t sequence, std::chrono::seconds timeout) {
    std::unique_lock<std::mutex> lock(mutex_);
    const auto key = std::make_pair(robot, sequence);
    if (!cv_.wait_for(lock, timeout, [&] { return seen_.count(key) != 0; })) return std::nullopt;
    return seen_.at(key);
  }
  mapmerge::client::Statistics statistics() const { return client_.statistics(); }

 private:
  static mapmerge::client::Options options(int domain) {
    mapmerge::client::Options o;
    o.domain = domain;
    return o;
  }
  std::mutex mutex_;
  std::condition_variable cv_;
  std::map<std::pair<std::string, std::uint64_t>, Clock::time_point> seen_;
  mapmerge::Client client_;  // last: its callbacks stop before the members they use go
};

struct Result {
  int n = 0, aligned = 0;
  double first_global_s = 0, all_aligned_s = -1, map_kb_per_robot = 0;
  std::vector<double> incremental_ms;
  std::vector<double> encode_ms, arrival_ms, receiver_decode_ms;  ///< parts of incremental_ms (raw receiver)
  std::uint64_t patched = 0, received = 0;  ///< global maps the client receiver patched, of those it received
  double cpu_s = 0, peak_rss_mb = 0, end_rss_mb = 0, max_rot_deg = 0, max_trans_m = 0;
  std::map<std::string, std::vector<double>> stages;  ///< server-side stage -> ms per incremental update
};

/// The server's own stage times of single-robot updates, from its log: check and store of the
/// map; fuse, encode, poses, store and publish of the global map it triggered.
std::map<std::string, std::vector<double>> incremental_stages(const std::string& log_path) {
  std::map<std::string, std::vector<double>> stages;
  std::ifstream log(log_path);
  for (std::string line; std::getline(log, line);) {
    double a = 0, b = 0, c = 0, d = 0, e = 0, f = 0, g = 0;
    const auto accepted = line.find("; check ");
    if (accepted != std::string::npos && std::sscanf(line.c_str() + accepted, "; check %lf ms, store %lf ms", &a, &b) == 2) {
      stages["map check"].push_back(a);
      stages["map store"].push_back(b);
      continue;
    }
    if (line.find("(1 re-fused, 1 by difference") == std::string::npos) continue;
    const auto at = line.find("(fuse ");
    if (at != std::string::npos &&
        std::sscanf(line.c_str() + at, "(fuse %lf: diff %lf, place %lf for %*u cubes; encode %lf, poses %lf, store %lf, publish %lf)",
                    &a, &f, &g, &b, &c, &d, &e) == 7) {
      stages["global fuse"].push_back(a);
      stages["global fuse: diff"].push_back(f);
      stages["global fuse: place"].push_back(g);
      stages["global encode"].push_back(b);
      stages["poses"].push_back(c);
      stages["global store"].push_back(d);
      stages["global publish"].push_back(e);
    }
  }
  return stages;
}

double secs(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

/// Robot i's map and the same map grown by `grow` m at both ends along x (its next update; the
/// fleet's end robots grow inwards), same frame.
struct BenchRobot {
  mt::RobotMap map, grown;
};

std::vector<BenchRobot> make_robots(const octomap::OcTree& world, int n, double share, double grow, std::mt19937& rng) {
  double x0, y0, z0, x1, y1, z1;
  world.getMetricMin(x0, y0, z0);
  world.getMetricMax(x1, y1, z1);
  const double length = std::max((x1 - x0) * share, 2.0 * (x1 - x0) / (n + 1)), step = n > 1 ? ((x1 - x0) - length) / (n - 1) : 0.0;
  std::uniform_real_distribution<double> yaw(-180, 180), tilt(-3, 3), off(-5, 5);
  std::vector<BenchRobot> robots;
  for (int i = 0; i < n; ++i) {
    auto box = [&](double extra) {
      return Eigen::AlignedBox3d(Eigen::Vector3d(x0 + i * step - extra, y0, z0), Eigen::Vector3d(x0 + i * step + length + extra, y1, z1));
    };
    const Eigen::Matrix4d T = i == 0 ? Eigen::Matrix4d::Identity()
                                     : mapmerge::paper_transform(off(rng), off(rng), 0, tilt(rng), tilt(rng), yaw(rng));
    const std::string id = "r" + std::to_string(i + 1);
    robots.push_back({mt::cut_robot_map(world, id, box(0), T), mt::cut_robot_map(world, id, box(grow), T)});
  }
  return robots;
}

int aligned_count(const mt::FleetListener& op) {
  int n = 0;
  for (const auto& [id, p] : op.poses()) n += p.status == 1 ? 1 : 0;
  return n;
}

void first_alignment(const Options& o, Result& r, mt::FleetListener& op, const std::vector<BenchRobot>& fleet,
                     std::vector<std::unique_ptr<mt::RobotPublisher>>& pubs) {
  std::vector<mt::RobotMap> robots;
  for (const auto& b : fleet) robots.push_back(b.map);
  const auto t0 = Clock::now();
  for (std::size_t i = 0; i < robots.size(); ++i) pubs[i]->publish(*robots[i].tree, "s1", 1);
  op.wait_for([&] { return op.globals_received() > 0; }, std::chrono::seconds(o.timeout_s));
  r.first_global_s = secs(t0);
  const bool all = op.wait_for([&] {
    return op.global().contributors.size() == robots.size();
  }, std::chrono::seconds(o.timeout_s));
  if (all) r.all_aligned_s = secs(t0);
  const auto merged = static_cast<int>(op.global().contributors.size());
  op.wait_for([&] { return aligned_count(op) >= merged; }, std::chrono::seconds(10));
  r.aligned = aligned_count(op);
  for (std::size_t i = 1; i < robots.size(); ++i) {
    const auto poses = op.poses();
    auto it = poses.find(robots[i].id);
    if (it == poses.end() || it->second.status != 1) continue;
    const Eigen::Matrix4d truth = robots[0].T_robot_world * robots[i].T_robot_world.inverse();
    r.max_rot_deg = std::max(r.max_rot_deg, mt::rotation_error_deg(truth, it->second.T_global_robot));
    r.max_trans_m = std::max(r.max_trans_m, mt::translation_error_m(truth, it->second.T_global_robot));
  }
}

/// Known robots in turn publish their next map (grown, then back to the original: a changed map
/// each time, as a mapping robot sends); latency until the global map holds that sequence.
void incremental(const Options& o, Result& r, mt::FleetListener& op, ClientReceiver* client,
                 const std::vector<BenchRobot>& fleet, std::vector<std::unique_ptr<mt::RobotPublisher>>& pubs) {
  std::vector<mt::RobotMap> robots;
  for (const auto& b : fleet) robots.push_back(b.map);
  const auto global = op.global();
  std::vector<std::size_t> known;
  for (std::size_t i = 0; i < robots.size(); ++i) {
    if (global.contributor_sequence.count(robots[i].id)) known.push_back(i);
  }
  if (known.empty()) return;
  Clock::time_point last_start;
  for (int u = 0; u < o.updates; ++u) {
    const std::size_t i = known[static_cast<std::size_t>(u) % known.size()];
    const std::uint64_t seq = 2 + static_cast<std::uint64_t>(u);
    const bool grown = (u / known.size()) % 2 == 0;
    if (u > 0 && o.period_s > 0.0) {
      std::this_thread::sleep_until(last_start + std::chrono::duration_cast<Clock::duration>(
                                                     std::chrono::duration<double>(o.period_s)));
    }
    const auto t0 = Clock::now();
    last_start = t0;
    const auto bytes = mapmerge::encode_map(grown ? *fleet[i].grown.tree : *fleet[i].map.tree,
                                            mapmerge::Encoding::kOctomapBt);
    const auto t_encoded = Clock::now();
    pubs[i]->publish_bytes(bytes, robots[i].id, "s1", seq);
    const auto ms = [](Clock::duration d) { return std::chrono::duration<double, std::milli>(d).count(); };
    if (client != nullptr) {  // the fleet's receiver: our client library
      if (const auto t = client->wait(robots[i].id, seq, std::chrono::seconds(120))) {
        r.incremental_ms.push_back(ms(*t - t0));
        r.encode_ms.push_back(ms(t_encoded - t0));
      }
      continue;
    }
    if (op.wait_for([&] { return op.global().contributor_sequence[robots[i].id] == seq; }, std::chrono::seconds(120))) {
      const auto g = op.global();
      r.incremental_ms.push_back(ms(g.received - t0));
      r.encode_ms.push_back(ms(t_encoded - t0));
      r.arrival_ms.push_back(ms(g.arrived - t_encoded));
      r.receiver_decode_ms.push_back(ms(g.received - g.arrived));
    }
  }
}

Result run(const Options& o, int n) {
  Result r;
  r.n = n;
  const auto world = mt::load_data_map(o.map);
  std::mt19937 rng(1234 + static_cast<unsigned>(n));
  const auto robots = make_robots(*world, n, o.strip_share, o.grow, rng);
  double bytes = 0;
  for (const auto& rb : robots) bytes += static_cast<double>(mapmerge::encode_map(*rb.map.tree, mapmerge::Encoding::kOctomapBt).size());
  r.map_kb_per_robot = bytes / n / 1024.0;
  const std::string dir = mt::temp_dir("bench_" + std::to_string(n));
  std::ofstream(dir + "/bench.yaml") << "publish: {min_interval_s: 0.0}\nmerge: {threads: 2}\n";
  mt::ServerProcess server({"--domain", std::to_string(o.domain), "--profile", "local", "--state-dir", dir + "/state", "--config",
                            dir + "/bench.yaml", "--reference", "r1", "--log-level", o.log_level},
                           dir + "/server.log");
  mt::FleetListener op(o.domain);
  std::unique_ptr<ClientReceiver> client;
  if (o.receiver == "client") {
    client = std::make_unique<ClientReceiver>(o.domain);
    op.observe_globals([](std::uint64_t, const std::map<std::string, std::uint64_t>&) {}, false);  // no decoding here
  }
  std::vector<std::unique_ptr<mt::RobotPublisher>> pubs;
  for (const auto& rb : robots) pubs.push_back(std::make_unique<mt::RobotPublisher>(o.domain, rb.map.id));
  std::this_thread::sleep_for(std::chrono::seconds(1));  // discovery settles
  first_alignment(o, r, op, robots, pubs);
  incremental(o, r, op, client.get(), robots, pubs);
  if (client) {
    r.patched = client->statistics().global_maps_patched;
    r.received = client->statistics().global_maps_received;
  }
  const auto stats = mapmerge::bench::proc_stats(server.pid());
  r.cpu_s = stats.cpu_s;
  r.peak_rss_mb = stats.hwm_mb;
  r.end_rss_mb = stats.rss_mb;
  server.kill(SIGTERM);
  r.stages = incremental_stages(dir + "/server.log");
  return r;
}

/// The middle value (upper median) of `v`; -1 when empty.
double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v.empty() ? -1.0 : v[v.size() / 2];
}

void print(const Result& r) {
  auto v = r.incremental_ms;
  std::sort(v.begin(), v.end());
  const double med = v.empty() ? -1 : v[v.size() / 2], mx = v.empty() ? -1 : v.back();
  const double p95 = v.empty() ? -1 : v[static_cast<std::size_t>(std::ceil(0.95 * static_cast<double>(v.size()))) - 1];
  std::printf("| %2d | %2d | %6.1f | %7.1f | %3zu | %6.0f | %6.0f | %6.0f | %5.2f | %4.2f | %7.1f | %6.0f | %5.1f | %6.0f | %5.3f |\n",
              r.n, r.aligned, r.first_global_s, r.all_aligned_s, v.size(), med, p95, mx, r.max_rot_deg, r.max_trans_m,
              r.cpu_s, r.peak_rss_mb, r.peak_rss_mb / r.n, r.end_rss_mb, r.map_kb_per_robot / 1024.0);
  std::fflush(stdout);
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"mapmerge-server end-to-end bench (loopback, real server process)"};
  Options o;
  app.add_option("--robots", o.robots, "fleet sizes")->delimiter(',');
  app.add_option("--map", o.map, "map in data/")->check(CLI::Validator(mt::data_map_problem, "FILE in data/"));
  app.add_option("--domain", o.domain, "DDS domain")->check(CLI::Range(0, 101));
  app.add_option("--updates", o.updates, "incremental updates measured per fleet size");
  app.add_option("--timeout", o.timeout_s, "seconds to wait for the whole fleet to be merged");
  app.add_option("--strip-share", o.strip_share, "share of the map's length each robot sees");
  app.add_option("--log-level", o.log_level, "the server's log level");
  app.add_option("--period", o.period_s,
                 "seconds from one update's start to the next (0: each right after the last was received)");
  app.add_option("--grow", o.grow, "an incremental update grows the robot's map by this much [m]");
  app.add_option("--receiver", o.receiver,
                 "who receives the global map: client (a mapmerge::Client observer, which patches changed blocks) or raw "
                 "(a listener decoding every map, with the latency split into arrival and decode)")
      ->check(CLI::IsMember({"client", "raw"}));
  CLI11_PARSE(app, argc, argv);
  std::printf("map %s; columns: robots | aligned | first global [s] | all merged [s] | incremental updates measured, "
              "median/p95/max [ms] | "
              "max rot err [deg] | max trans err [m] | server CPU [s] | peak RSS [MB] | peak RSS/robot [MB] | RSS at the end [MB] | "
              "map/robot [MB]\n",
              o.map.c_str());
  std::printf("|  N | al | first  | all     | n   | incr50 | incr95 | incrMx | rot   | tr   | cpu     | rss    | rss/r | rssEnd | map   |\n");
  std::vector<Result> results;
  for (int n : o.robots) {
    results.push_back(run(o, n));
    print(results.back());
  }
  std::printf("\nserver stages of incremental updates, median ms (map check/store: every accepted map)\n");
  for (const Result& r : results) {
    std::printf("N=%2d:", r.n);
    if (o.receiver == "client") {
      std::printf(" [outside the server: robot encode %.1f; client receiver patched %llu of %llu global maps]",
                  median(r.encode_ms), static_cast<unsigned long long>(r.patched), static_cast<unsigned long long>(r.received));
    } else {
      std::printf(" [outside the server: robot encode %.1f; publish -> global arrived %.1f; receiver decode %.1f]",
                  median(r.encode_ms), median(r.arrival_ms), median(r.receiver_decode_ms));
    }
    for (const auto& [stage, v] : r.stages) {
      std::printf(" %s %.1f;", stage.c_str(), median(v));
    }
    std::printf("\n");
  }
  return 0;
}
