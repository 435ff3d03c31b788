#include "mapmerge/server/global_map.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <utility>

#include <spdlog/spdlog.h>

#include "mapmerge/map/bounds.hpp"
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
  if (auto ref = registry.get(registry.reference()); ref && ref->map) return ref->map->resolution();
  double res = maps.front().map->resolution();
  for (const auto& m : maps) res = std::min(res, m.map->resolution());
  return res;
}

}  // namespace

std::vector<PlacedMap> GlobalMapBuilder::placed_maps(const Registry& registry,
                                                     std::vector<Contribution>& contributors) {
  std::vector<PlacedMap> maps;
  for (const auto& [robot, pose] : registry.poses()) {
    const auto rec = registry.get(robot);
    if (!rec || !rec->map) continue;
    if (!config_.merge.keep_lost_maps && !registry.presence(robot).alive) continue;  // gone: left out
    Eigen::Matrix4d T = pose.T_global_robot;
    double keep = 0.0;
    const auto fused = fusion_ ? fusion_->pose_of(robot) : std::nullopt;
    if (fused && *fused != T) {
      const double half_voxel = 0.5 * fusion_->resolution();
      if (max_displacement(*fused, T, *fusion_->extent_of(robot)) < half_voxel) {
        // No voxel of what is fused moves by half a voxel: keep the fused pose. A new map's leaves
        // are checked too, by GlobalFusion::set, after it has found the difference.
        if (fusion_->map_of(robot) == rec->map) {
          T = *fused;
        } else {
          keep = half_voxel;
        }
      }
    }
    maps.push_back(PlacedMap{robot, rec->map, T, keep});
    contributors.push_back(Contribution{robot, rec->session_id, rec->sequence});
  }
  return maps;
}

bool GlobalMapBuilder::defer_moves(std::vector<PlacedMap>& maps, std::vector<Contribution>& contributors) {
  bool grown = false;  // a map to fuse by its difference (cheap)
  std::vector<std::size_t> moves, moved;  // maps to fuse whole (costly): new robots, then new poses
  bool any_fused = false;
  bool later = false;  // a robot's content goes out now, its move in the next builds
  std::vector<std::size_t> stepping;  // robots moving in steps
  const bool steps = config_.publish.move_step_leaves > 0;
  const auto fused_contribution = [&](std::size_t i) {
    const auto c = fused_contributions_.find(maps[i].robot);
    if (c != fused_contributions_.end()) contributors[i] = c->second;
  };
  for (std::size_t i = 0; i < maps.size(); ++i) {
    PlacedMap& m = maps[i];
    const auto fused = fusion_->pose_of(m.robot);
    any_fused |= fused.has_value();
    if (fusion_->holds(m.robot, m.map.get(), m.T_global_robot)) continue;
    const auto fused_map = fusion_->map_of(m.robot);
    if (fusion_->moving(m.robot)) {
      // Halfway through a move in steps, to the pose it is moving to. A new map goes in now by its
      // difference (each part at the pose its place is fused at) and the move goes on with it in
      // the builds after; otherwise its next step. A new pose, or a map without a checked body to
      // diff, waits for the move's end (finishing the move at once would hold everyone's updates).
      const bool new_map =
          m.map != fused_map && m.map->binary_body() && fusion_->fuses_by_difference(m.robot, *m.map);
      later |= m.T_global_robot != *fused || (m.map != fused_map && !new_map);  // held: a build after
      m.T_global_robot = *fused;
      m.keep_pose_within = 0.0;
      if (new_map) {
        grown = true;  // its content goes out now; its step (sync_global's second set()) as any other
      } else if (m.map != fused_map) {
        m.map = fused_map;
        fused_contribution(i);
      }
      stepping.push_back(i);
      continue;
    }
    // A moved robot with a new map its difference can fuse: its content can go out first.
    const bool new_content = fused && fused_map != m.map && fusion_->fuses_by_difference(m.robot, *m.map);
    if (fused && (*fused == m.T_global_robot || m.keep_pose_within > 0.0)) {
      grown = true;  // (a kept pose that set() finds too far after all is moved in this build)
    } else if (steps && new_content) {
      // Its content now, by difference at the fused pose; its move (the same map, so in steps)
      // from the next build on.
      m.T_global_robot = *fused;
      later = grown = true;
      moves_held_ = true;  // held back once: the next build moves it, grown maps or not
    } else {
      grown |= new_content;
      (fused ? moved : moves).push_back(i);
    }
  }
  // Grown maps go out alone, without the steps of a move (~0.1 s each), but only every other
  // build: a stream of updates never holds a move back for good.
  if (!stepping.empty()) {
    const bool hold = grown && !step_held_;
    for (const std::size_t i : stepping) maps[i].hold_step = hold;
    step_held_ = hold;
  }
  moves.insert(moves.end(), moved.begin(), moved.end());
  if (moves.empty() || !any_fused) return later;  // a first fusion is built whole
  // Grown maps go out first, alone (a known robot's update is on the fleet's latency path), but
  // only every other build: a stream of updates never holds moves back for good.
  const bool moves_now = !grown || std::exchange(moves_held_, false);
  const std::size_t budget = config_.publish.move_nodes_per_build;
  std::vector<bool> keep(maps.size(), true);
  std::size_t nodes = 0, taken = 0;
  for (const std::size_t i : moves) {
    const std::size_t n = maps[i].map->num_nodes();
    if (moves_now && (taken == 0 || budget == 0 || nodes + n <= budget)) {
      nodes += n;
      ++taken;
    } else {
      keep[i] = false;
    }
  }
  moves_held_ = taken == 0;
  if (taken == moves.size()) return later;
  for (std::size_t i = maps.size(); i-- > 0;) {
    if (keep[i]) continue;
    const auto fused = fusion_->pose_of(maps[i].robot);
    if (fused) {  // at its fused pose: the new map by difference there, else the map fused then
      maps[i].T_global_robot = *fused;
      if (!fusion_->fuses_by_difference(maps[i].robot, *maps[i].map)) {
        maps[i].map = fusion_->map_of(maps[i].robot);
        fused_contribution(i);
      }
    } else {  // not yet in the global map: a next build fuses it
      maps.erase(maps.begin() + static_cast<std::ptrdiff_t>(i));
      contributors.erase(contributors.begin() + static_cast<std::ptrdiff_t>(i));
    }
  }
  return true;
}

std::optional<GlobalMapOut> GlobalMapBuilder::build(const Registry& registry, std::uint64_t version) {
  const auto t0 = std::chrono::steady_clock::now();
  unchanged_ = false;
  GlobalMapOut g;
  std::vector<PlacedMap> maps = placed_maps(registry, g.contributors);
  if (maps.empty()) return std::nullopt;
  const double resolution = global_resolution(registry, config_, maps);
  if (!(resolution > 0.0) || !std::isfinite(resolution)) return std::nullopt;
  if (!fusion_ || fusion_->resolution() != resolution) {
    FuseConfig fc;
    fc.max_work = config_.limits.max_fusion_work;
    fusion_ = std::make_unique<GlobalFusion>(resolution, fc);
    refused_.clear();
    last_built_.reset();  // nothing encoded to patch
    g.contributors.clear();
    maps = placed_maps(registry, g.contributors);  // no fused poses to keep in a new fusion
  }
  deferred_ = defer_moves(maps, g.contributors);
  for (const PlacedMap& m : maps) {  // freed by release_replaced(), after the map is out
    if (auto old = fusion_->map_of(m.robot); old && old != m.map) replaced_.push_back(std::move(old));
  }
  const GlobalSync sync = sync_global(*fusion_, maps, refused_, config_.publish.move_step_leaves);
  deferred_ |= sync.moving > 0;  // the next build takes their next step
  for (const auto& [robot, reason] : sync.skipped) {
    spdlog::warn("robot {}: map left out of the global map: {}", robot, reason);
  }
  if (sync.fused.empty()) return std::nullopt;
  g.contributors.erase(std::remove_if(g.contributors.begin(), g.contributors.end(),
                                      [&](const Contribution& c) {
                                        return std::find(sync.fused.begin(), sync.fused.end(), c.robot_id) ==
                                               sync.fused.end();
                                      }),
                       g.contributors.end());
  for (const Contribution& c : g.contributors) fused_contributions_[c.robot_id] = c;
  const auto t1 = std::chrono::steady_clock::now();
  const Encoding encoding = parse_encoding(config_.publish.global_encoding).value_or(Encoding::kOctomapBt);
  GlobalFusion::Encoded e = fusion_->encode();
  g.data = encoding == Encoding::kOctomapBt ? std::move(e.bt) : encode_map(*fusion_->tree(), encoding);
  g.ros_body = std::move(e.body);
  g.hash = payload_hash(g.data);
  stages_ = Stages{std::chrono::duration<double>(t1 - t0).count(),
                   std::chrono::duration<double>(std::chrono::steady_clock::now() - t1).count(), sync.updated,
                   sync.incremental, sync.from_bodies, sync.cubes, sync.diff_s, sync.place_s, sync.moving};
  const auto same = [](const Contribution& a, const Contribution& b) {
    return a.robot_id == b.robot_id && a.session_id == b.session_id && a.sequence == b.sequence;
  };
  if (last_built_ && g.hash == last_built_->second && g.contributors.size() == last_contributors_.size() &&
      std::equal(g.contributors.begin(), g.contributors.end(), last_contributors_.begin(), same)) {
    unchanged_ = true;  // e.g. a refinement moved a robot by less than half a voxel: no new version
    return std::nullopt;
  }
  last_contributors_ = g.contributors;
  if (e.patches && last_built_ && encoding == Encoding::kOctomapBt) {  // blocks of the canonical body only
    g.delta = GlobalMapOut::Delta{last_built_->first, last_built_->second, std::move(*e.patches)};
  }
  last_built_ = std::make_pair(version, g.hash);
  g.version = version;
  g.stamp_unix = unix_now();
  g.frame_id = config_.merge.global_frame;
  g.resolution = resolution;
  g.encoding = to_string(encoding);
  return g;
}

Provenance GlobalMapBuilder::provenance() const { return fusion_ ? fusion_->provenance() : Provenance{}; }

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
