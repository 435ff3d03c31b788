#pragma once
/// What crosses between the DDS layer and the pipeline, free of any DDS vendor type.

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "mapmerge/map/global_delta.hpp"

namespace mapmerge::server {

/// One incoming robot map, native (MapUpdate) or ROS 2 (octomap_msgs/Octomap).
struct MapSample {
  std::string robot_id;        ///< as written in the sample (native) or taken from the topic (ROS 2)
  std::string topic_robot;     ///< the robot id the topic name carries
  std::string topic;
  std::string session_id;
  std::uint64_t sequence = 0;
  std::string frame_id;
  double resolution = 0.0;     ///< [m]
  std::string encoding;        ///< native: "octomap-bt", ...; ROS 2: empty
  bool ros = false;            ///< data is a bare tree body (octomap_msgs)
  bool ros_binary = true;      ///< octomap_msgs `binary`
  std::string ros_id;          ///< octomap_msgs `id` ("OcTree")
  std::vector<std::uint8_t> data;
  double received_unix = 0.0;  ///< arrival [s since epoch]
};

enum class PoseState { kUnknown, kAligned, kRejected };

struct PoseOut {
  std::string robot_id;
  std::string robot_frame;
  Eigen::Matrix4d T_global_robot = Eigen::Matrix4d::Identity();
  double fitness = 0.0;
  double quality = 0.0;
  PoseState state = PoseState::kUnknown;
};

struct Contribution {
  std::string robot_id;
  std::string session_id;
  std::uint64_t sequence = 0;
};

/// The global map as published (also what the store keeps to republish after a restart).
struct GlobalMapOut {
  std::uint64_t version = 0;
  double stamp_unix = 0.0;
  std::string frame_id;
  double resolution = 0.0;
  std::string encoding;               ///< encoding of `data`
  std::vector<std::uint8_t> data;     ///< the native payload
  std::vector<std::uint8_t> ros_body; ///< the octomap_msgs body (writeBinaryData)
  std::vector<Contribution> contributors;
  std::uint64_t hash = 0;             ///< payload_hash(data)
  /// The change from the version built before (GlobalMapDelta), when a receiver holding that
  /// version can patch it into this one; published once, with the map, never stored.
  struct Delta {
    std::uint64_t base_version = 0;
    std::uint64_t base_hash = 0;
    std::vector<BlockPatch> blocks;
  };
  std::optional<Delta> delta;
};

struct MergeReportOut {
  std::string target;
  std::string source;
  bool accepted = false;
  bool global_search = true;
  double fitness = 0.0;
  double duration_s = 0.0;
  std::string detail;
  double stamp_unix = 0.0;
};

struct RobotStateOut {
  std::string robot_id;
  PoseState state = PoseState::kUnknown;
  std::string session_id;
  std::uint64_t sequence = 0;
  double resolution = 0.0;
  std::uint64_t accepted = 0;
  std::uint64_t rejected = 0;
  std::uint64_t ignored = 0;     ///< duplicate and out-of-order updates
  std::string last_error;
  bool alive = false;            ///< a writer of its map topic is matched
  std::uint32_t times_lost = 0;  ///< how often it was lost since start
};

struct StatusOut {
  std::uint64_t global_version = 0;
  std::vector<RobotStateOut> robots;
  std::vector<MergeReportOut> recent_merges;
  std::uint64_t updates_received = 0;
  std::uint64_t updates_rejected = 0;
  std::uint64_t updates_ignored = 0;  ///< duplicate and out-of-order updates
  std::uint64_t merges_run = 0;
  std::uint64_t merges_coalesced = 0;
  bool store_ok = true;              ///< the last store write succeeded (or no store)
  std::string store_error;           ///< why the store failed
  std::uint64_t store_failures = 0;  ///< failed store writes since start
  std::uint64_t store_pending = 0;   ///< writes held in memory until the store works again
  std::uint64_t merges_queued = 0;   ///< robots waiting for a worker now
  std::uint64_t merges_queued_max = 0;  ///< most robots ever waiting at once
  std::uint64_t merges_running = 0;  ///< jobs running now (robots' turns and idle work)
};

double unix_now();

}  // namespace mapmerge::server
