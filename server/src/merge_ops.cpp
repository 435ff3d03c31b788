#include "mapmerge/server/merge_ops.hpp"

#include <algorithm>
#include <cmath>
#include <exception>

#include <Eigen/Geometry>

#include "mapmerge/graph/information.hpp"
#include "mapmerge/map/bounds.hpp"
#include "mapmerge/map/fusion.hpp"
#include "mapmerge/map/map_io.hpp"
#include "mapmerge/wire/topics.hpp"

namespace mapmerge::server {

double estimate_overlap(const octomap::OcTree& target, const octomap::OcTree& source,
                        const Eigen::Matrix4d& T_target_source, std::size_t samples) {
  const Eigen::AlignedBox3d target_box = leaf_bounds(target);
  const Eigen::AlignedBox3d source_box = leaf_bounds(source);
  if (target_box.isEmpty() || source_box.isEmpty()) return 0.0;
  Eigen::AlignedBox3d moved;  // the source's box in the target frame (axis-aligned hull)
  for (int c = 0; c < 8; ++c) {
    moved.extend((T_target_source * source_box.corner(static_cast<Eigen::AlignedBox3d::CornerType>(c)).homogeneous())
                     .head<3>());
  }
  if (!moved.intersects(target_box)) return 0.0;
  std::size_t occupied = 0;
  for (auto it = source.begin_leafs(), end = source.end_leafs(); it != end; ++it) occupied += source.isNodeOccupied(*it);
  const std::size_t stride = std::max<std::size_t>(1, occupied / std::max<std::size_t>(1, samples));
  const double r = target.getResolution();
  std::size_t seen = 0, hit = 0, i = 0;
  for (auto it = source.begin_leafs(), end = source.end_leafs(); it != end; ++it) {
    if (!source.isNodeOccupied(*it) || (i++ % stride) != 0) continue;
    const Eigen::Vector3d p = (T_target_source * Eigen::Vector4d(it.getX(), it.getY(), it.getZ(), 1.0)).head<3>();
    ++seen;
    bool found = false;  // an occupied target voxel within one voxel
    for (int dx = -1; dx <= 1 && !found; ++dx)
      for (int dy = -1; dy <= 1 && !found; ++dy)
        for (int dz = -1; dz <= 1 && !found; ++dz) {
          const auto* n = target.search(p.x() + dx * r, p.y() + dy * r, p.z() + dz * r);
          found = n != nullptr && target.isNodeOccupied(n);
        }
    hit += found ? 1 : 0;
  }
  return seen == 0 ? 0.0 : static_cast<double>(hit) / static_cast<double>(seen);
}

DecodedMap decode_sample(const MapSample& s, const DecodeLimits& limits) {
  DecodedMap out;
  if (!wire::is_valid_robot_id(s.robot_id)) {
    out.reason = "invalid robot id '" + s.robot_id + "'";
    return out;
  }
  if (s.robot_id != s.topic_robot) {
    out.reason = "robot id '" + s.robot_id + "' does not match its topic " + s.topic;
    return out;
  }
  CheckedMap r = s.ros ? check_tree_body(s.ros_id, s.resolution, s.ros_binary, s.data, limits)
                       : check_map(s.data, s.encoding, limits);
  if (!r.ok()) {
    out.reason = std::string(to_string(r.error)) + ": " + r.reason;
    return out;
  }
  if (r.empty || !r.map || r.map->num_nodes() == 0) {
    out.reason = "empty map";
    return out;
  }
  if (!s.ros && s.resolution > 0.0 && std::abs(r.map->resolution() - s.resolution) > 1e-9) {
    out.reason = "resolution field " + std::to_string(s.resolution) + " differs from the map's " +
                 std::to_string(r.map->resolution());
    return out;
  }
  out.map = std::move(r.map);
  return out;
}

std::shared_ptr<const align::PreparedMap> prepare(std::shared_ptr<const octomap::OcTree> tree,
                                                  const align::AlignConfig& config, bool features, std::string& error) {
  try {
    return std::make_shared<const align::PreparedMap>(features ? align::prepare_map(std::move(tree), config)
                                                               : align::prepare_for_refine(std::move(tree), config));
  } catch (const std::exception& e) {
    error = e.what();
    return nullptr;
  }
}

align::AlignResult align_global(const align::PreparedMap& target, const align::PreparedMap& source,
                                const align::AlignConfig& config) {
  return align::align(target, source, config);
}

align::AlignResult align_local(const align::PreparedMap& target, const align::PreparedMap& source,
                               const Eigen::Matrix4d& T_target_source, const align::AlignConfig& config) {
  return align::refine(target, source, T_target_source, config);
}

Edge make_edge(const RobotRecord& target, const RobotRecord& source, const align::AlignResult& result) {
  Edge e{target.robot_id, source.robot_id, result.T_target_source, result.fitness};
  e.inliers = result.inliers;
  e.overlap = result.overlap;
  if (target.map && source.map) {
    const Eigen::Isometry3d T(result.T_target_source);
    e.pivot_source = graph::overlap_pivot(leaf_bounds(*source.map->tree()), leaf_bounds(*target.map->tree()), T);
  }
  const graph::EdgeInformation info =
      graph::information_from_alignment({e.inliers, e.fitness, e.overlap, e.pivot_source});
  if (info.valid) e.information = info.information;  // else left zero: the registry's fallback
  return e;
}

bool moved_noticeably(const Eigen::Matrix4d& before, const Eigen::Matrix4d& after, double translation,
                      double rotation_deg) {
  const Eigen::Matrix4d d = rigid_inverse(before) * after;
  const double angle = std::acos(std::clamp((d.topLeftCorner<3, 3>().trace() - 1.0) / 2.0, -1.0, 1.0));
  return d.topRightCorner<3, 1>().norm() > translation || angle * 180.0 / M_PI > rotation_deg;
}

GlobalSync sync_global(GlobalFusion& fusion, const std::vector<PlacedMap>& maps, RefusedMaps& refused) {
  GlobalSync out;
  for (const std::string& robot : fusion.robots()) {
    const bool listed = std::any_of(maps.begin(), maps.end(), [&](const PlacedMap& m) { return m.robot == robot; });
    if (!listed) fusion.remove(robot);
  }
  for (const PlacedMap& m : maps) {
    if (fusion.holds(m.robot, m.map.get(), m.T_global_robot)) {
      out.fused.push_back(m.robot);
      continue;
    }
    const auto r = refused.find(m.robot);
    if (r != refused.end() && r->second.first.lock() == m.map && r->second.second == m.T_global_robot) continue;
    try {
      const GlobalFuseResult res = fusion.set(m.robot, m.map, m.T_global_robot);  // !ok: robot left out
      if (!res.ok) throw MapError(res.reason);
      refused.erase(m.robot);
      out.fused.push_back(m.robot);
      ++out.updated;
      out.incremental += res.incremental ? 1 : 0;
      out.from_bodies += res.from_bodies ? 1 : 0;
    } catch (const std::exception& e) {
      fusion.remove(m.robot);
      refused[m.robot] = {m.map, m.T_global_robot};
      out.skipped.emplace_back(m.robot, e.what());
    }
  }
  return out;
}

}  // namespace mapmerge::server
