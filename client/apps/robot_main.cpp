// mapmerge-robot: act as a robot publishing its map to the mapmerge server, and print the pose
// the server publishes for it.

#include <iostream>
#include <memory>
#include <mutex>
#include <optional>

#include <octomap/OcTree.h>

#include "cli_common.hpp"
#include "mapmerge/map/map_io.hpp"

namespace {

using namespace mapmerge;
using namespace std::chrono;

struct RobotConfig {
  std::string id;
  std::string map_file;
  std::string frame_id;
  double rate_hz = 1.0;      ///< publications per second [Hz]
  int repeat = 1;            ///< publications in all; 0: until stopped
  bool zstd = false;
  double timeout_s = 0.0;    ///< stop after this long; 0: until SIGINT/SIGTERM [s]
  bool exit_when_aligned = false;
  bool json = false;
  cli::DdsFlags dds;
};

constexpr milliseconds kFlushTimeout{2000};  ///< waiting for acks of the last update on exit

/// A pose worth printing again: another status, global version or transform.
bool changed(const client::Pose& a, const client::Pose& b) {
  return a.status != b.status || a.global_version != b.global_version || a.translation != b.translation ||
         a.rotation != b.rotation;
}

int run(const RobotConfig& config) {
  std::unique_ptr<octomap::OcTree> tree;
  try {
    tree = read_octree_file(config.map_file);
  } catch (const std::exception& e) {
    cli::err("mapmerge-robot: " + std::string(e.what()));
    return cli::kExitUsage;
  }
  client::Options options = cli::client_options(config.dds);
  options.robot_id = config.id;
  options.frame_id = config.frame_id;
  options.zstd = config.zstd;
  options.receive_global_map = false;  // a simulated robot needs only its pose
  const auto vendor = *client::parse_vendor(config.dds.vendor);
  std::unique_ptr<Client> robot = make_client(options, vendor);

  // With --json, stdout carries only pose lines.
  (config.json ? cli::err : cli::out)(config.id + ": " + client::to_string(vendor) + " on domain " + std::to_string(config.dds.domain) +
           ", profile " + config.dds.profile + ", session " + robot->session_id() + ", map " + config.map_file +
           " (" + std::to_string(tree->size()) + " nodes, " + std::to_string(tree->getResolution()) + " m)");
  std::atomic<bool> aligned{false};
  std::optional<client::Pose> last_printed;  // callback thread only
  robot->on_own_pose([&](const client::Pose& pose) {
    if (pose.status == client::PoseStatus::kAligned) aligned = true;
    if (last_printed && !changed(*last_printed, pose)) return;  // the server republishes periodically
    last_printed = pose;
    cli::out(config.json ? cli::pose_json(pose).dump() : config.id + ": pose " + cli::pose_text(pose));
  });
  robot->on_server_connection([&](bool connected) {
    cli::err(config.id + (connected ? ": server connected" : ": server lost; carrying on"));
  });
  robot->on_warning([&](const std::string& message) { cli::err(config.id + ": " + message); });

  const auto start = steady_clock::now();
  const auto period = duration_cast<milliseconds>(duration<double>(1.0 / config.rate_hz));
  auto next_publish = start;
  int published = 0;
  for (;;) {
    if (cli::stop_requested()) break;
    if (config.exit_when_aligned && aligned) break;
    const auto now = steady_clock::now();
    if (config.timeout_s > 0 && now - start >= duration<double>(config.timeout_s)) {
      robot->flush(kFlushTimeout);
      if (config.exit_when_aligned) {
        cli::err(config.id + ": not aligned within " + std::to_string(config.timeout_s) + " s");
        return cli::kExitTimeout;
      }
      return cli::kExitOk;
    }
    if ((config.repeat == 0 || published < config.repeat) && now >= next_publish) {
      const client::PublishResult r = robot->publish(*tree);
      if (!r.queued) {
        cli::err(config.id + ": " + r.error);
        return cli::kExitFailure;
      }
      ++published;
      next_publish += period;
      if (!config.json) {
        cli::out(config.id + ": published update #" + std::to_string(r.sequence_number) + " (" +
                 std::to_string(r.bytes) + " bytes, " + r.encoding + ")");
      }
    }
    cli::sleep_interruptible(milliseconds(20));
  }
  robot->flush(kFlushTimeout);
  return cli::kExitOk;
}

}  // namespace

int main(int argc, char** argv) {
  RobotConfig config;
  CLI::App app("mapmerge-robot: act as a robot publishing its OctoMap to the mapmerge server; prints its pose in "
               "the global frame whenever the server publishes a new one.\n"
               "Exit codes: 0 done or stopped (SIGINT/SIGTERM), 1 DDS failure, 2 bad flags or unreadable map, "
               "3 --timeout reached before alignment (with --exit-when-aligned).",
               "mapmerge-robot");
  app.add_option("--id", config.id, "robot id (a letter, then letters, digits or '_')")->required();
  app.add_option("--map", config.map_file, "the robot's map, .bt or .ot")->required()->check(CLI::ExistingFile);
  app.add_option("--frame-id", config.frame_id, "the robot's map frame (default <id>/map)");
  app.add_option("--rate", config.rate_hz, "publications per second [Hz]")
      ->check(CLI::Range(0.001, 100.0))
      ->capture_default_str();
  app.add_option("--repeat", config.repeat, "how many times to publish the map (0: until stopped)")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  app.add_flag("--zstd", config.zstd, "compress the map (encoding octomap-bt+zstd)");
  app.add_option("--timeout", config.timeout_s, "stop after this many seconds (0: run until SIGINT/SIGTERM)")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();
  app.add_flag("--exit-when-aligned", config.exit_when_aligned, "exit 0 once the server aligned this robot");
  app.add_flag("--json", config.json, "print poses as JSON lines (as mapmerge-listen --json)");
  cli::add_dds_flags(app, config.dds);
  int code = 0;
  if (!cli::parse(app, argc, argv, code)) return code;

  client::Options probe = cli::client_options(config.dds);
  probe.robot_id = config.id;
  if (const std::string error = cli::check_flags(config.dds, probe); !error.empty()) {
    std::cerr << "mapmerge-robot: " << error << std::endl;
    return cli::kExitUsage;
  }
  cli::setup_output(config.dds.verbose);
  cli::install_signal_handlers();
  try {
    return run(config);
  } catch (const client::ClientError& e) {
    cli::err(std::string("mapmerge-robot: ") + e.what());
    return cli::kExitFailure;
  } catch (const std::exception& e) {
    cli::err(std::string("mapmerge-robot: ") + e.what());
    return cli::kExitFailure;
  }
}
