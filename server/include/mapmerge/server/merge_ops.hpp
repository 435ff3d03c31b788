#pragma once
/// The only place the server calls core: decoding a received map, preparing it for alignment,
/// pairwise alignment (global or local) and fusion of the aligned maps. Each is one function,
/// so the server follows core's API in one file.

#include <memory>
#include <string>
#include <utility>
#include <vector>

#include <Eigen/Core>
#include <octomap/OcTree.h>

#include "mapmerge/align/align.hpp"
#include "mapmerge/map/map_codec.hpp"
#include "mapmerge/server/messages.hpp"
#include "mapmerge/server/registry.hpp"

namespace mapmerge::server {

struct DecodedMap {
  std::shared_ptr<const octomap::OcTree> tree;  ///< null when rejected
  std::string reason;                           ///< why rejected
};

/// Validates and decodes a received map (native payload or ROS 2 tree body); a robot id that
/// does not match its topic is rejected too.
DecodedMap decode_sample(const MapSample& sample, const DecodeLimits& limits);

/// Alignment features of a map (sharing the tree, not copying it); null with `error` set for a
/// map that cannot be aligned.
std::shared_ptr<const align::PreparedMap> prepare(std::shared_ptr<const octomap::OcTree> tree,
                                                  const align::AlignConfig& config, std::string& error);

/// Global search for T_target_source (no initial guess).
align::AlignResult align_global(const align::PreparedMap& target, const align::PreparedMap& source,
                                const align::AlignConfig& config);

/// Local refinement from a known T_target_source.
align::AlignResult align_local(const align::PreparedMap& target, const align::PreparedMap& source,
                               const Eigen::Matrix4d& T_target_source, const align::AlignConfig& config);

/// The accepted alignment `T_target_source` of `source`'s map into `target`'s as a graph edge
/// with its quality (inliers, fitness, overlap; pivot: centre of the maps' bounding-box overlap).
Edge make_edge(const RobotRecord& target, const RobotRecord& source, const align::AlignResult& result);

/// One robot's map with its pose in the global frame.
struct PlacedMap {
  std::string robot;                 ///< robot id (for skip reports)
  std::shared_ptr<const octomap::OcTree> tree;
  Eigen::Matrix4d T_global_robot = Eigen::Matrix4d::Identity();
};

/// The fused global tree and the robots left out of it.
struct FusedGlobal {
  std::unique_ptr<octomap::OcTree> tree;  ///< null when nothing could be fused
  std::vector<std::string> fused;         ///< robots whose map is in `tree`, in input order
  std::vector<std::pair<std::string, std::string>> skipped;  ///< (robot, reason) left out
};

/// Fuses the maps into a new global tree of `resolution` [m] (log-odds addition, resampled).
/// A map that core refuses (non-rigid pose, fusion work above `max_work`, MapError or any other
/// exception) is skipped with its reason; the others are fused regardless.
FusedGlobal fuse_global(const std::vector<PlacedMap>& maps, double resolution, double max_work);

}  // namespace mapmerge::server
