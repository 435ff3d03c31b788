#pragma once
/// The fleet the server tests share: robots cut from geb079 (8 cm) with known frames, and a
/// fixture that starts mapmerge-server on the test's own DDS domain and state directory.

#include <memory>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "child_process.hpp"
#include "dds_test_env.hpp"
#include "fleet.hpp"
#include "sanitizer.hpp"
#include "mapmerge/map/crop.hpp"

namespace mapmerge::test {

using namespace std::chrono_literals;

/// Generous: 2 shared cores; kSanitizerSlowdown times under AddressSanitizer, where one global
/// search of these maps takes 20-80 s while another test runs on the other core, and three robots
/// that align only in a chain (r1 <- r2, then r2 <- r3 after r1 <- r3 fails whole and block by
/// block) took 207 s of a 240 s wait (ServerFaults.FleetConverges..., 2026-12-06).
constexpr auto kMergeTimeout = std::chrono::seconds(120 * kSanitizerSlowdown);
constexpr double kMaxRotationDeg = 2.0;
constexpr double kMaxTranslationM = 0.3;  ///< ~4 voxels of geb079 (8 cm), after chaining two merges

inline Eigen::AlignedBox3d strip(double x0, double x1) {
  return Eigen::AlignedBox3d(Eigen::Vector3d(x0, -8, -1), Eigen::Vector3d(x1, 8, 4));
}

/// Three robots along the geb079 corridor, overlapping their neighbours by 8-10 m, each in a
/// random frame.
struct Fleet {
  std::shared_ptr<const octomap::OcTree> world = load_data_map("geb079.bt");
  std::vector<RobotMap> robots{
      cut_robot_map(*world, "r1", strip(-8, 12), mapmerge::paper_transform(1, 2, 0, 0, 0, 30)),
      cut_robot_map(*world, "r2", strip(4, 24), mapmerge::paper_transform(-4, 7, 0.3, -3, 2, 155)),
      cut_robot_map(*world, "r3", strip(14, 31), mapmerge::paper_transform(5, -3, 0.2, 2, -1, -70))};
  /// The truth: T_global_robot = T_r1_world * T_robot_world^-1.
  Eigen::Matrix4d truth(std::size_t i) const { return robots[0].T_robot_world * robots[i].T_robot_world.inverse(); }
};

inline const Fleet& fleet() {
  static const Fleet f;
  return f;
}

class ServerFleet : public ::testing::Test {
 protected:
  int domain = dds_domain();
  std::string dir = temp_dir(::testing::UnitTest::GetInstance()->current_test_info()->name());

  std::vector<std::string> server_args(const std::vector<std::string>& extra = {}) const {
    std::vector<std::string> args{"--domain", std::to_string(domain), "--profile", "local", "--state-dir",
                                  dir + "/state"};
    args.insert(args.end(), extra.begin(), extra.end());
    return args;
  }
  std::unique_ptr<ServerProcess> start_server(const std::vector<std::string>& extra = {}) const {
    return std::make_unique<ServerProcess>(server_args(extra), dir + "/server.log");
  }
  static bool aligned(const FleetListener& l, const std::vector<std::string>& ids) {
    const auto poses = l.poses();
    for (const auto& id : ids) {
      auto it = poses.find(id);
      if (it == poses.end() || it->second.status != 1) return false;
    }
    return true;
  }
  static bool global_has(const FleetListener& l, std::size_t contributors) {
    return l.global().contributors.size() >= contributors;
  }
  /// Killed Fast DDS processes leave shared-memory segments behind: remove the unused ones.
  static void clean_shm() { [[maybe_unused]] int rc = std::system("fastdds shm clean >/dev/null 2>&1"); }
};

}  // namespace mapmerge::test
