#pragma once
/// Runs the real mapmerge-server on a fresh state directory, with robot maps cut from a real
/// map by `mapmerge scenario` (known ground truth), for end-to-end tests.

#include <array>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <memory>
#include <string>

#include <gtest/gtest.h>
#include <octomap/OcTree.h>
#include <nlohmann/json.hpp>

#include "child_process.hpp"
#include "dds_test_env.hpp"
#include "sanitizer.hpp"

namespace mapmerge::test {

namespace fs = std::filesystem;

inline const std::string kBin = std::string(MAPMERGE_BINARY_DIR) + "/bin/";

/// Rotation angle [deg] and translation distance [m] between two row-major 4x4 transforms.
struct PoseError {
  double rotation_deg = 0.0;
  double translation_m = 0.0;
};
inline PoseError pose_error(const std::array<double, 16>& truth, const std::array<double, 16>& estimate) {
  double trace = 0.0;  // trace(R_true^T R_est)
  for (int i = 0; i < 3; ++i) {
    for (int k = 0; k < 3; ++k) trace += truth[k * 4 + i] * estimate[k * 4 + i];
  }
  const double c = std::max(-1.0, std::min(1.0, (trace - 1.0) / 2.0));
  PoseError e;
  e.rotation_deg = std::acos(c) * 180.0 / M_PI;
  e.translation_m = std::hypot(truth[3] - estimate[3], truth[7] - estimate[7], truth[11] - estimate[11]);
  return e;
}

/// Occupied volume of a map [m^3] (independent of how far the tree is pruned).
inline double occupied_volume(const octomap::OcTree& tree) {
  double volume = 0.0;
  for (auto it = tree.begin_leafs(), end = tree.end_leafs(); it != end; ++it) {
    if (tree.isNodeOccupied(*it)) volume += std::pow(it.getSize(), 3);
  }
  return volume;
}

class ServerFixture : public ::testing::Test {
 protected:
  static constexpr double kMaxRotationErrorDeg = 3.0;    ///< accepted pose error vs truth [deg]
  static constexpr double kMaxTranslationErrorM = 0.3;   ///< accepted pose error vs truth [m]

  void SetUp() override {
    dir_ = fs::temp_directory_path() / ("mapmerge_e2e_" + std::to_string(::getpid()) + "_" +
                                        ::testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::remove_all(dir_);
    fs::create_directories(dir_);
    // Two robots, 40-50 % overlap, each in its own random frame; r1 defines the global frame.
    ChildProcess scenario(kBin + "mapmerge",
                          {"scenario", std::string(MAPMERGE_DATA_DIR) + "/fr_079.bt", "-o", dir_.string(), "-n", "2",
                           "--min-overlap", "0.4", "--max-overlap", "0.5", "--seed", "3"},
                          Logs::split((dir_ / "scenario").string()));
    ASSERT_EQ(scenario.wait(std::chrono::seconds(120 * test::kSanitizerSlowdown)), 0) << scenario.err();
    std::ifstream in(dir_ / "truth.json");
    truth_ = nlohmann::json::parse(in);
  }

  void TearDown() override {
    stop_server();
    fs::remove_all(dir_);
  }

  void start_server() {
    server_ = std::make_unique<ServerProcess>(
        std::vector<std::string>{"--domain", std::to_string(dds_domain()), "--profile", "local", "--state-dir",
                                 (dir_ / "state").string(), "--reference", "r1"},
        (dir_ / ("server" + std::to_string(++server_runs_) + ".log")).string());
  }
  /// SIGTERM (clean) or SIGKILL (crash); a killed Fast DDS process's shared memory is cleaned.
  void stop_server(int sig = SIGTERM) {
    if (!server_) return;
    server_->kill(sig, std::chrono::seconds(30));
    server_.reset();
    if (sig == SIGKILL) std::system("fastdds shm clean >/dev/null 2>&1");
  }
  std::string server_log() const {
    return server_ ? server_->log() : std::string();
  }

  std::string map_path(const std::string& robot) const { return (dir_ / (robot + ".bt")).string(); }
  std::array<double, 16> true_pose(const std::string& robot) const {
    for (const auto& r : truth_["robots"]) {
      if (r["id"] == robot) {
        std::array<double, 16> m{};
        for (int i = 0; i < 16; ++i) m[i] = r["T_global_robot"][i].get<double>();
        return m;
      }
    }
    ADD_FAILURE() << "no truth for " << robot;
    return {};
  }

  fs::path dir_;
  nlohmann::json truth_;
  std::unique_ptr<ServerProcess> server_;
  int server_runs_ = 0;
};

}  // namespace mapmerge::test
