#pragma once
/// The only place the server calls core: decoding a received map, preparing it for alignment,
/// pairwise alignment (global or local) and fusion of the aligned maps. Each is one function,
/// so the server follows core's API in one file.

#include <map>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include <Eigen/Core>
#include <octomap/OcTree.h>

#include "mapmerge/align/align.hpp"
#include "mapmerge/map/global_fusion.hpp"
#include "mapmerge/map/map_codec.hpp"
#include "mapmerge/server/messages.hpp"
#include "mapmerge/server/registry.hpp"

namespace mapmerge::server {

struct DecodedMap {
  std::shared_ptr<const HeldMap> map;  ///< null when rejected
  std::string reason;                  ///< why rejected
};

/// Validates a received map (native payload or ROS 2 tree body) as decoding does, without
/// building the tree of a binary body (HeldMap builds it when needed); a robot id that does not
/// match its topic is rejected too.
DecodedMap decode_sample(const MapSample& sample, const DecodeLimits& limits);

/// Alignment features of a map, read off its bytes (its octree is not built); null with `error` set
/// for a map that cannot be aligned.
/// Without `features` only stages 1-2 (enough for align_local, not for align_global).
std::shared_ptr<const align::PreparedMap> prepare(const HeldMap& map, const align::AlignConfig& config,
                                                  bool features, std::string& error);

/// Global search for T_target_source (no initial guess); `cancel` stops it between its steps.
align::AlignResult align_global(const align::PreparedMap& target, const align::PreparedMap& source,
                                const align::AlignConfig& config, const align::Cancel& cancel = {});

/// The rescue's global search on denser features (align::rescue), for a pair the search refused.
align::AlignResult align_rescue(const align::PreparedMap& target, const align::PreparedMap& source,
                                const align::AlignConfig& config, const align::Cancel& cancel = {});

/// Local refinement from a known T_target_source.
align::AlignResult align_local(const align::PreparedMap& target, const align::PreparedMap& source,
                               const Eigen::Matrix4d& T_target_source, const align::AlignConfig& config);

/// The accepted alignment `T_target_source` of `source`'s map into `target`'s as a graph edge
/// with its quality (inliers, fitness, overlap; pivot: centre of the maps' bounding-box overlap).
Edge make_edge(const RobotRecord& target, const RobotRecord& source, const align::AlignResult& result);

/// One robot's map with its pose in the global frame.
struct PlacedMap {
  std::string robot;                 ///< robot id (for skip reports)
  std::shared_ptr<const HeldMap> map;
  Eigen::Matrix4d T_global_robot = Eigen::Matrix4d::Identity();
  /// GlobalFusion::set's keep_pose_within [m]: a fused robot whose map changed is fused at its
  /// fused pose when no leaf of the map lands this far from where T_global_robot puts it.
  double keep_pose_within = 0.0;
  /// A robot moving in steps (GlobalFusion::moving) takes no step in this sync: it stays as it is
  /// (a new map of it still goes in, by its difference).
  bool hold_step = false;
};

/// Whether `after` is more than `translation` [m] or `rotation_deg` [deg] away from `before`.
bool moved_noticeably(const Eigen::Matrix4d& before, const Eigen::Matrix4d& after, double translation,
                      double rotation_deg);

/// What one sync_global() did.
struct GlobalSync {
  std::vector<std::string> fused;    ///< robots whose map is in the global map, in input order
  std::vector<std::pair<std::string, std::string>> skipped;  ///< (robot, reason) left out
  std::size_t updated = 0;           ///< robots (re)fused by this sync
  std::size_t incremental = 0;       ///< ... of which only the difference (same pose, grown map)
  std::size_t from_bodies = 0;       ///< ... of which diffed on the maps' binary bodies
  std::size_t cubes = 0;             ///< changed leaf regions placed on the global grid
  double diff_s = 0.0, place_s = 0.0;  ///< GlobalFuseResult's, summed over the robots
  std::size_t moving = 0;            ///< robots whose move in steps is not finished
};

/// Robot -> the map and pose a fusion refused: not tried again until either changes.
using RefusedMaps = std::map<std::string, std::pair<std::weak_ptr<const HeldMap>, Eigen::Matrix4d>>;

/// Brings `fusion` to exactly `maps`: robots not listed are taken out, a robot whose map or pose
/// changed is updated (only the difference of its map when the pose is the same). A map that core
/// refuses (non-rigid pose, fusion work above the fusion's max_work, any exception) is left out
/// with its reason (and remembered in `refused`); the others are fused regardless.
/// `move_step`: GlobalFusion::set()'s (a robot's move to a new pose, this many leaves a call).
GlobalSync sync_global(GlobalFusion& fusion, const std::vector<PlacedMap>& maps, RefusedMaps& refused,
                       std::size_t move_step = 0);

}  // namespace mapmerge::server
