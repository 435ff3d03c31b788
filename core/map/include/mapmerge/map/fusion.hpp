#pragma once
/// Stage 9 of the pipeline: fusing octrees by adding log-odds (occupied and free space both).
///
/// Every source leaf, pruned or not, is resampled at the target's resolution: a target voxel takes
/// the log-odds of the source leaf that contains its centre (for source leaves at least one target
/// voxel wide), so rotated maps leave no holes and nothing is counted twice. Source leaves smaller
/// than a target voxel (a finer source) each vote for the voxel holding their centre; the largest
/// vote per voxel is added (occupied wins, as OctoMap's inner nodes take their children's maximum).
/// Evidence is added to the target node's log-odds and clamped to the target's clamping thresholds.

#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include <Eigen/Core>
#include <octomap/OcTree.h>

#include "mapmerge/map/provenance.hpp"

namespace mapmerge {

/// Settings of fuse_into().
struct FuseConfig {
  bool fuse_free = true;             ///< also add the (negative) evidence of free leaves
  bool prune = true;                 ///< prune the target when done (inner nodes are always
                                     ///< updated; skip pruning when fusing several maps in a row)
  double rigid_tolerance = 1e-6;     ///< max |R^T R - I| entry accepted as a rotation [-]
  double max_work = 5e8;             ///< refuse sources whose leaves would cost more target
                                     ///< voxel visits than this (bound: n^3 for a leaf n target
                                     ///< voxels wide, its surface 27 (n+1)^2 when n > 4); real
                                     ///< Freiburg maps need ~2e7; a hostile huge leaf ~1e10 [-]
};

/// What fuse_into() did; `ok == false` leaves the target untouched.
struct FuseResult {
  bool ok = false;
  std::string reason;                   ///< why it failed (empty when ok)
  std::size_t source_leaves = 0;        ///< source leaves read
  std::size_t voxel_updates = 0;        ///< single target voxels updated
  std::size_t block_updates = 0;        ///< aligned target blocks updated in one step
  std::size_t leaves_clipped = 0;       ///< source leaves (partly) outside the target key space
};

/// Adds `source`'s evidence, moved into `target`'s frame by `T_target_source` (rigid), to
/// `target`. Resolutions may differ. With `provenance`, every target voxel that receives occupied
/// evidence records `robot` unless a robot with stronger evidence for it is recorded already.
FuseResult fuse_into(octomap::OcTree& target, const octomap::OcTree& source,
                     const Eigen::Matrix4d& T_target_source, const FuseConfig& config);
FuseResult fuse_into(octomap::OcTree& target, const octomap::OcTree& source,
                     const Eigen::Matrix4d& T_target_source, const FuseConfig& config,
                     Provenance* provenance, std::uint16_t robot);

/// One map and its pose in the global frame.
using MapInGlobal = std::pair<const octomap::OcTree*, Eigen::Matrix4d>;

/// Fuses N maps (each with T_global_map) into a new tree of the given resolution [m], in order.
/// Throws MapError if a transform is not rigid or the resolution is not positive.
std::unique_ptr<octomap::OcTree> fuse_maps(const std::vector<MapInGlobal>& maps_in_global,
                                           double resolution);

/// fuse_maps() that also says which map (index into `maps_in_global`) contributed each occupied
/// voxel, for `mapmerge render --by-robot`. Robot frames are left for the caller to fill in.
struct FusedMap {
  std::unique_ptr<octomap::OcTree> tree;
  Provenance provenance;
};
FusedMap fuse_maps_with_provenance(const std::vector<MapInGlobal>& maps_in_global,
                                   double resolution);

}  // namespace mapmerge
