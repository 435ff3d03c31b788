// mapmerge-listen: watch the fleet as an operator would: print every robot's pose and status
// and save the current global map.

#include <cstdio>
#include <map>
#include <iostream>
#include <memory>
#include <mutex>

#include <octomap/OcTree.h>

#include "cli_common.hpp"
#include "mapmerge/map/map_io.hpp"

namespace {

using namespace mapmerge;
using namespace std::chrono;

struct ListenConfig {
  std::string output;         ///< save the global map here; empty: do not
  bool json = false;
  double timeout_s = 0.0;     ///< give up after this long; 0: never [s]
  int until_aligned = 0;      ///< exit once this many robots are aligned; 0: never
  double map_wait_s = 15.0;   ///< with -o and --until-aligned: wait this long for a global map
                              ///< of the aligned poses' version [s]
  cli::DdsFlags dds;
};

constexpr milliseconds kRequestPeriod{2000};  ///< re-ask for the map while waiting for it

/// Saves global maps as they arrive (atomically: a reader never sees half a file).
class MapSaver {
 public:
  explicit MapSaver(std::string path) : path_(std::move(path)) {}
  void save(const client::GlobalMap& map) {
    if (path_.empty()) return;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      if (saved_ && saved_version_ == map.version) return;  // a republished version
    }
    const std::string tmp = path_ + ".tmp.bt";
    write_octree_file(*map.tree, tmp);
    if (std::rename(tmp.c_str(), path_.c_str()) != 0) throw std::runtime_error("cannot rename " + tmp + " to " + path_);
    std::lock_guard<std::mutex> lock(mutex_);
    saved_version_ = map.version;
    saved_ = true;
  }
  bool saved(std::uint64_t min_version) const {
    std::lock_guard<std::mutex> lock(mutex_);
    return saved_ && saved_version_ >= min_version;
  }
  bool saved_any() const { return saved(0); }

 private:
  std::string path_;
  mutable std::mutex mutex_;
  bool saved_ = false;
  std::uint64_t saved_version_ = 0;
};

std::string map_text(const client::GlobalMap& map) {
  std::string s = "global map v" + std::to_string(map.version) + ": " + std::to_string(map.tree->size()) +
                  " nodes, " + std::to_string(map.payload_bytes) + " bytes, frame " + map.frame_id + ", robots";
  for (const auto& c : map.contributors) s += " " + c.robot_id + "#" + std::to_string(c.sequence_number);
  return s;
}

/// Robots aligned now, and the highest global version among their poses.
std::pair<int, std::uint64_t> aligned_count(const std::vector<client::Pose>& poses) {
  int n = 0;
  std::uint64_t version = 0;
  for (const auto& p : poses) {
    if (p.status != client::PoseStatus::kAligned) continue;
    ++n;
    version = std::max(version, p.global_version);
  }
  return {n, version};
}

int run(const ListenConfig& config) {
  client::Options options = cli::client_options(config.dds);
  options.receive_global_map = true;
  const auto vendor = *client::parse_vendor(config.dds.vendor);
  std::unique_ptr<Client> listener = make_client(options, vendor);
  MapSaver saver(config.output);
  std::atomic<bool> save_failed{false};

  listener->on_pose([&](const client::Pose& pose) {
    cli::out(config.json ? cli::pose_json(pose).dump() : pose.robot_id + ": " + cli::pose_text(pose));
  });
  listener->on_global_map([&](const std::shared_ptr<const client::GlobalMap>& map) {
    if (!config.json) cli::out(map_text(*map));
    try {
      saver.save(*map);
    } catch (const std::exception& e) {
      cli::err(std::string("mapmerge-listen: ") + e.what());
      save_failed = true;
    }
  });
  listener->on_server_connection(
      [](bool connected) { cli::err(connected ? "mapmerge-listen: server connected" : "mapmerge-listen: server lost"); });
  listener->on_warning([](const std::string& message) { cli::err("mapmerge-listen: " + message); });

  const auto start = steady_clock::now();
  std::optional<steady_clock::time_point> goal_reached;
  auto last_request = start;
  while (!cli::stop_requested()) {
    if (save_failed) return cli::kExitFailure;
    const auto now = steady_clock::now();
    if (config.until_aligned > 0) {
      const auto [n, version] = aligned_count(listener->poses());
      if (n >= config.until_aligned) {
        if (config.output.empty() || saver.saved(version)) return cli::kExitOk;
        if (!goal_reached) goal_reached = now;
        if (now - last_request >= kRequestPeriod) {
          listener->request_global_map();
          last_request = now;
        }
        if (now - *goal_reached >= duration<double>(config.map_wait_s)) {
          if (saver.saved_any()) {
            cli::err("mapmerge-listen: saved global map is older than the poses' version " + std::to_string(version));
            return cli::kExitOk;
          }
          cli::err("mapmerge-listen: " + std::to_string(n) + " robots aligned but no global map received for -o");
          return cli::kExitNoMap;
        }
      }
    }
    if (config.timeout_s > 0 && now - start >= duration<double>(config.timeout_s)) {
      if (config.until_aligned > 0) {
        cli::err("mapmerge-listen: timeout: " + std::to_string(aligned_count(listener->poses()).first) + " of " +
                 std::to_string(config.until_aligned) + " robots aligned after " + std::to_string(config.timeout_s) +
                 " s");
        return cli::kExitTimeout;
      }
      if (!config.output.empty() && !saver.saved_any()) {
        cli::err("mapmerge-listen: timeout: no global map received");
        return cli::kExitTimeout;
      }
      return cli::kExitOk;
    }
    cli::sleep_interruptible(milliseconds(20));
  }
  return cli::kExitOk;
}

}  // namespace

int main(int argc, char** argv) {
  ListenConfig config;
  CLI::App app("mapmerge-listen: print every robot's pose and status as the mapmerge server publishes them, and "
               "save the current global map.\n"
               "Exit codes: 0 done or stopped (SIGINT/SIGTERM), 1 DDS or file failure, 2 bad flags, 3 --timeout "
               "reached first, 4 --until-aligned reached but no global map arrived for -o.",
               "mapmerge-listen");
  app.add_option("-o,--output", config.output, "save the global map here (.bt), replaced atomically on each version");
  app.add_flag("--json", config.json,
               "one JSON object per line per pose: {\"robot\", \"status\", \"T_global_robot\" (16 numbers, "
               "row-major), \"fitness\", \"global_version\"}");
  app.add_option("--timeout", config.timeout_s, "give up after this many seconds (0: never)")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  app.add_option("--until-aligned", config.until_aligned,
                 "exit 0 as soon as this many robots are aligned (with -o: and their global map is saved)")
      ->check(CLI::NonNegativeNumber);
  app.add_option("--map-wait", config.map_wait_s,
                 "with -o and --until-aligned: seconds to wait for the matching global map")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  cli::add_dds_flags(app, config.dds);
  int code = 0;
  if (!cli::parse(app, argc, argv, code)) return code;

  client::Options probe = cli::client_options(config.dds);
  if (const std::string error = cli::check_flags(config.dds, probe); !error.empty()) {
    std::cerr << "mapmerge-listen: " << error << std::endl;
    return cli::kExitUsage;
  }
  cli::setup_output(config.dds.verbose);
  cli::install_signal_handlers();
  try {
    return run(config);
  } catch (const std::exception& e) {
    cli::err(std::string("mapmerge-listen: ") + e.what());
    return cli::kExitFailure;
  }
}
