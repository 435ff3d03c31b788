#pragma once
/// Test fleet around a real mapmerge-server: robots publishing maps cut from a real map with
/// known transforms, and a listener holding the latest global map and poses.

#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <octomap/OcTree.h>

#include "mapmerge/wire/fastdds.hpp"

namespace mapmerge::test {

/// A robot's map: the part of `world` inside `box`, moved into the robot's frame.
struct RobotMap {
  std::string id;
  std::shared_ptr<const octomap::OcTree> tree;
  Eigen::Matrix4d T_robot_world = Eigen::Matrix4d::Identity();
};
RobotMap cut_robot_map(const octomap::OcTree& world, const std::string& id, const Eigen::AlignedBox3d& box,
                       const Eigen::Matrix4d& T_robot_world);
std::shared_ptr<const octomap::OcTree> load_data_map(const std::string& name);
/// Why load_data_map(name) cannot work (no such file in data/), or "" (a CLI11 check for benches).
std::string data_map_problem(const std::string& name);

/// A robot publishing native MapUpdates on rt/<id>/mapmerge/map.
class RobotPublisher {
 public:
  /// `security`: the robot's DDS Security identity (default: off).
  RobotPublisher(int domain, const std::string& id, const wire::ProfileSpec& profile = {},
                 const wire::SecurityOptions& security = {});
  ~RobotPublisher();
  /// Publishes `tree` (sequence numbers count from 1 unless given).
  void publish(const octomap::OcTree& tree, const std::string& session = "s1", std::uint64_t sequence = 0);
  /// Publishes raw bytes as a map update (for bad input).
  void publish_bytes(const std::vector<std::uint8_t>& bytes, const std::string& robot_field,
                     const std::string& session, std::uint64_t sequence);

 private:
  std::string id_;
  std::uint64_t sequence_ = 0;
  std::unique_ptr<wire::FastddsParticipant> participant_;
  eprosima::fastdds::dds::DataWriter* writer_ = nullptr;
};

/// A ROS 2 robot as octomap_server publishes: octomap_msgs/Octomap (binary) on rt/<id>/octomap_binary.
class RosRobotPublisher {
 public:
  RosRobotPublisher(int domain, const std::string& id);
  ~RosRobotPublisher();
  void publish(const octomap::OcTree& tree);

 private:
  std::string id_;
  std::unique_ptr<wire::FastddsParticipant> participant_;
  eprosima::fastdds::dds::DataWriter* writer_ = nullptr;
};

struct ReceivedPose {
  Eigen::Matrix4d T_global_robot = Eigen::Matrix4d::Identity();
  int status = 0;  ///< mapmerge::PoseStatus: 0 unknown, 1 aligned, 2 rejected
  std::uint64_t global_version = 0;
  double fitness = 0.0;
};

struct ReceivedGlobal {
  std::uint64_t version = 0;
  std::shared_ptr<octomap::OcTree> tree;
  std::vector<std::string> contributors;
  std::map<std::string, std::uint64_t> contributor_sequence;  ///< robot -> map sequence fused
  std::chrono::steady_clock::time_point received;  ///< when it was decoded (or taken, if not decoded)
  std::chrono::steady_clock::time_point arrived;   ///< when the sample reached the listener
};

struct ReceivedMerge {
  std::string target, source;
  bool accepted = false;
  bool global_search = true;
  std::string detail;  ///< e.g. "extra pair, ...", "rejected by the pose graph: ..."
};

/// The last server status seen.
struct ReceivedStatus {
  std::uint64_t updates_received = 0, updates_rejected = 0, updates_ignored = 0, merges_run = 0, merges_coalesced = 0;
  std::uint64_t global_version = 0;
  std::map<std::string, std::uint64_t> accepted;  ///< per robot: updates accepted
  std::map<std::string, std::uint64_t> sequence;  ///< per robot: sequence number of the map held
  std::map<std::string, std::uint64_t> rejected;  ///< per robot: updates rejected
  std::map<std::string, std::uint64_t> ignored;   ///< per robot: duplicate and out-of-order updates
  std::map<std::string, double> resolution;       ///< per robot: resolution of the map held [m]
  std::map<std::string, std::string> last_error;
  std::map<std::string, std::string> session;     ///< per robot: session of the map held
  std::map<std::string, bool> alive;              ///< per robot: a map writer is matched
  std::map<std::string, std::uint32_t> times_lost;
  bool store_ok = true;
  std::string store_error;
  std::uint64_t store_failures = 0, store_pending = 0;
  std::uint64_t merges_queued = 0, merges_queued_max = 0;
  std::uint64_t merges_running = 0;               ///< jobs the server runs now
  std::size_t count = 0;                          ///< status samples received
};

/// What the server has acknowledged to the fleet over everything received (all server runs):
/// the state a restarted server must still hold.
struct Acknowledged {
  /// Per robot and session: the highest sequence the server reported holding (status topic) or
  /// fused (global map contributors). Key "<robot>/<session>".
  std::map<std::string, std::uint64_t> sequence;
  std::map<std::string, Eigen::Matrix4d> aligned_pose;  ///< last aligned pose per robot
  std::uint64_t global_version = 0;                     ///< highest global map version received
  std::uint64_t version_regressions = 0;  ///< global maps older than one received before
};

/// An operator's view: latest global map (native and ROS 2), poses, tf child frames.
class FleetListener {
 public:
  /// `security`: the operator's DDS Security identity (an observer enclave; default: off).
  explicit FleetListener(int domain, const wire::ProfileSpec& profile = {}, const wire::SecurityOptions& security = {});
  ~FleetListener();

  /// Waits until `pred()` holds (checked on every sample and every 100 ms) or `timeout`.
  bool wait_for(const std::function<bool()>& pred, std::chrono::seconds timeout);
  /// Asks the server to republish (rt/mapmerge/request).
  void request();

  std::map<std::string, ReceivedPose> poses() const;
  ReceivedGlobal global() const;
  std::uint64_t ros_global_bytes() const;
  std::vector<std::string> tf_children() const;
  std::size_t globals_received() const;
  /// Every merge report seen on the status topic (deduplicated by pair, kind and stamp).
  std::vector<ReceivedMerge> merges() const;
  ReceivedStatus status() const;
  Acknowledged acknowledged() const;
  /// Called on the DDS thread for every global map with its contributors' sequences; with
  /// `decode` false the maps are no longer decoded (global() then has no tree): for benches.
  using GlobalObserver = std::function<void(std::uint64_t version, const std::map<std::string, std::uint64_t>&)>;
  void observe_globals(GlobalObserver observer, bool decode);

  struct Impl;

 private:
  std::unique_ptr<Impl> impl_;
};

/// Pose errors of an estimate against the truth.
double rotation_error_deg(const Eigen::Matrix4d& T_true, const Eigen::Matrix4d& T_est);
double translation_error_m(const Eigen::Matrix4d& T_true, const Eigen::Matrix4d& T_est);

/// Share of the occupied voxels of `expected` (every `stride`-th) that are occupied in `map`
/// within one voxel, after moving them by T_map_expected.
double occupied_coverage(const octomap::OcTree& map, const octomap::OcTree& expected,
                         const Eigen::Matrix4d& T_map_expected, int stride = 7);

/// occupied_coverage() of the operator's latest global map (0 before one was decoded), after
/// waiting up to `timeout` for it to exceed `share`. A grown map is fused at once with the pose
/// from before its refinement, which races the build: a later global map may be the placed one.
double global_coverage_after(FleetListener& op, const octomap::OcTree& expected, const Eigen::Matrix4d& T_global_expected,
                             double share, std::chrono::seconds timeout);

/// A fresh directory under the test's temp dir.
std::string temp_dir(const std::string& name);

}  // namespace mapmerge::test
