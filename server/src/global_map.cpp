#include "mapmerge/server/global_map.hpp"

#include <algorithm>

#include <spdlog/spdlog.h>

#include "mapmerge/server/merge_ops.hpp"

namespace mapmerge::server {
namespace {

PoseState to_pose_state(RobotStatus s) {
  switch (s) {
    case RobotStatus::kAligned: return PoseState::kAligned;
    case RobotStatus::kRejected: return PoseState::kRejected;
    case RobotStatus::kUnknown: break;
  }
  return PoseState::kUnknown;
}

/// The global resolution: configured, else the reference's, else the finest aligned map's.
double global_resolution(const Registry& registry, const ServerConfig& config, const std::vector<PlacedMap>& maps) {
  if (config.merge.global_resolution > 0.0) return config.merge.global_resolution;
  if (auto ref = registry.get(registry.reference()); ref && ref->tree) return ref->tree->getResolution();
  double res = maps.front().tree->getResolution();
  for (const auto& m : maps) res = std::min(res, m.tree->getResolution());
  return res;
}

}  // namespace

std::optional<GlobalMapOut> build_global_map(const Registry& registry, const ServerConfig& config,
                                             std::uint64_t version) {
  std::vector<PlacedMap> maps;
  GlobalMapOut g;
  for (const auto& [robot, pose] : registry.poses()) {
    const auto rec = registry.get(robot);
    if (!rec || !rec->tree) continue;
    maps.push_back(PlacedMap{robot, rec->tree, pose.T_global_robot});
    g.contributors.push_back(Contribution{robot, rec->session_id, rec->sequence});
  }
  if (maps.empty()) return std::nullopt;
  const double resolution = global_resolution(registry, config, maps);
  const FusedGlobal fused = fuse_global(maps, resolution, config.limits.max_fusion_work);
  for (const auto& [robot, reason] : fused.skipped) {
    spdlog::warn("robot {}: map left out of the global map: {}", robot, reason);
  }
  if (!fused.tree) return std::nullopt;
  g.contributors.erase(std::remove_if(g.contributors.begin(), g.contributors.end(),
                                      [&](const Contribution& c) {
                                        return std::find(fused.fused.begin(), fused.fused.end(), c.robot_id) ==
                                               fused.fused.end();
                                      }),
                       g.contributors.end());
  const auto& tree = fused.tree;
  const Encoding encoding = parse_encoding(config.publish.global_encoding).value_or(Encoding::kOctomapBt);
  g.version = version;
  g.stamp_unix = unix_now();
  g.frame_id = config.merge.global_frame;
  g.resolution = resolution;
  g.encoding = to_string(encoding);
  g.data = encode_map(*tree, encoding);
  g.ros_body = encode_tree_body(*tree, true);
  return g;
}

std::vector<PoseOut> pose_outputs(const Registry& registry) {
  const auto poses = registry.poses();
  std::vector<PoseOut> out;
  for (const auto& rec : registry.all()) {
    PoseOut p;
    p.robot_id = rec->robot_id;
    p.robot_frame = rec->frame_id.empty() ? rec->robot_id + "/map" : rec->frame_id;
    const auto it = poses.find(rec->robot_id);
    if (it != poses.end()) {
      p.T_global_robot = it->second.T_global_robot;
      p.fitness = it->second.fitness;
      p.quality = it->second.quality >= 0.0 ? it->second.quality : 1.0 / (1.0 + it->second.hops);
      p.state = PoseState::kAligned;
    } else {
      p.state = to_pose_state(registry.status(rec->robot_id));
    }
    out.push_back(p);
  }
  return out;
}

}  // namespace mapmerge::server
