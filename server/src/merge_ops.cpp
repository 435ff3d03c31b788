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

std::shared_ptr<const align::PreparedMap> prepare(const HeldMap& map, const align::AlignConfig& config,
                                                  bool features, std::string& error) {
  try {
    return std::make_shared<const align::PreparedMap>(features ? align::prepare_map(map, config)
                                                               : align::prepare_for_refine(map, config));
  } catch (const std::exception& e) {
    error = e.what();
    return nullptr;
  }
}

align::AlignResult align_global(const align::PreparedMap& target, const align::PreparedMap& source,
                                const align::AlignConfig& config, const align::Cancel& cancel) {
  return align::align(target, source, config, cancel);
}

align::AlignResult align_rescue(const align::PreparedMap& target, const align::PreparedMap& source,
                                const align::AlignConfig& config, const align::Cancel& cancel) {
  return align::rescue(target, source, config, cancel);
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
    e.pivot_source = graph::overlap_pivot(leaf_bounds(*source.map), leaf_bounds(*target.map), T);
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

GlobalSync sync_global(GlobalFusion& fusion, const std::vector<PlacedMap>& maps, RefusedMaps& refused,
                       std::size_t move_step) {
  GlobalSync out;
  for (const std::string& robot : fusion.robots()) {
    const bool listed = std::any_of(maps.begin(), maps.end(), [&](const PlacedMap& m) { return m.robot == robot; });
    if (!listed) fusion.remove(robot);
  }
  for (const PlacedMap& m : maps) {
    // A new map of a robot moving in steps goes in by its difference without a step (set()); its
    // step is a second set() of the same map, unless held, so that a robot publishing at every
    // build still ends its move.
    const bool new_map_moving = fusion.moving(m.robot) && fusion.map_of(m.robot) != m.map;
    if (m.hold_step && fusion.moving(m.robot) && !new_map_moving) {
      out.fused.push_back(m.robot);
      ++out.moving;
      continue;
    }
    if (fusion.holds(m.robot, m.map.get(), m.T_global_robot)) {
      out.fused.push_back(m.robot);
      continue;
    }
    const auto r = refused.find(m.robot);
    if (r != refused.end() && r->second.first.lock() == m.map && r->second.second == m.T_global_robot) continue;
    try {
      GlobalFuseResult res =
          fusion.set(m.robot, m.map, m.T_global_robot, m.keep_pose_within, move_step);  // !ok: left out
      if (!res.ok) throw MapError(res.reason);
      if (new_map_moving && res.moving && !m.hold_step) {
        const GlobalFuseResult step = fusion.set(m.robot, m.map, m.T_global_robot, 0.0, move_step);
        if (!step.ok) throw MapError(step.reason);
        res.cubes += step.cubes;
        res.place_s += step.place_s;
        res.moving = step.moving;
      }
      refused.erase(m.robot);
      out.fused.push_back(m.robot);
      ++out.updated;
      out.incremental += res.incremental ? 1 : 0;
      out.from_bodies += res.from_bodies ? 1 : 0;
      out.cubes += res.cubes;
      out.diff_s += res.diff_s;
      out.place_s += res.place_s;
      out.moving += res.moving ? 1 : 0;
    } catch (const std::exception& e) {
      fusion.remove(m.robot);
      refused[m.robot] = {m.map, m.T_global_robot};
      out.skipped.emplace_back(m.robot, e.what());
    }
  }
  return out;
}

}  // namespace mapmerge::server
