#pragma once
/// The published state, computed from the registry: the fused global map of every aligned
/// robot, and one pose per robot (aligned ones with T_global_robot, the others unknown).

#include <cstdint>
#include <map>
#include <memory>
#include <optional>
#include <vector>

#include <Eigen/Geometry>

#include "mapmerge/map/global_fusion.hpp"
#include "mapmerge/server/config.hpp"
#include "mapmerge/server/merge_ops.hpp"
#include "mapmerge/server/messages.hpp"
#include "mapmerge/server/registry.hpp"

namespace mapmerge::server {

/// Keeps the global map of the aligned robots up to date (core's GlobalFusion): each build
/// fuses only what changed since the last one. Used by one thread (the server's main loop).
class GlobalMapBuilder {
 public:
  explicit GlobalMapBuilder(const ServerConfig& config) : config_(config) {}

  /// The global map of every aligned robot (nothing when no robot is aligned). A robot whose pose
  /// moved so little since it was fused that no point of its map moves by half a global voxel
  /// keeps its fused pose (a refinement's or the pose graph's wobble does not re-fuse its map).
  /// Nothing either when the map and its contributors are those of the last build (unchanged()).
  std::optional<GlobalMapOut> build(const Registry& registry, std::uint64_t version);
  /// True when the last build found the global map as last built: no new version (the poses may
  /// still have moved, by less than half a voxel of any map point).
  bool unchanged() const { return unchanged_; }

  /// True when the last build left robots to fuse whole (new robots, moved poses) for the next
  /// builds (grown maps went first, or the move budget was spent): build again soon.
  bool deferred() const { return deferred_; }

  /// Which robot contributed each occupied voxel of the last built map, with every robot's frame.
  /// O(occupied voxels of all robots): call it off the publishing path.
  Provenance provenance() const;

  /// Time the last build spent per stage [s].
  struct Stages {
    double fuse_s = 0.0;    ///< bringing the fusion up to date
    double encode_s = 0.0;  ///< serialising the global map
    std::size_t updated = 0, incremental = 0;  ///< robots re-fused, of which only the difference
    std::size_t from_bodies = 0;  ///< ... of which read off the payloads' bytes (no tree walk)
    std::size_t cubes = 0;        ///< changed leaf regions placed (GlobalSync::cubes)
    double diff_s = 0.0, place_s = 0.0;  ///< parts of fuse_s: finding the change, placing it
    std::size_t moving = 0;              ///< robots halfway through a move in steps
  };
  Stages last_stages() const { return stages_; }
  /// Frees the maps the last build replaced in the fusion. build() keeps them: freeing a
  /// Freiburg-size octree takes ~30-60 ms, which the publishing path need not wait for.
  void release_replaced() { replaced_.clear(); }
  /// Bytes held by the global map's sums.
  std::size_t memory_usage() const { return fusion_ ? fusion_->memory_usage() : 0; }

 private:
  std::vector<PlacedMap> placed_maps(const Registry& registry, std::vector<Contribution>& contributors);
  const ServerConfig& config_;
  std::unique_ptr<GlobalFusion> fusion_;
  /// Maps to fuse whole (new robot, new pose) beyond publish.move_nodes_per_build (at least one),
  /// or all of them when some maps only grew and the last build did not hold all back too (grown
  /// maps reach the fleet first), are held back for this build; true if any was. A held-back
  /// robot that is fused keeps its fused pose, with its new map fused by difference there when
  /// the resolution is the same (its update's content goes out now, its move later); a moved robot
  /// with a new map of the same resolution counts as grown. A first
  /// fusion is whole.
  bool defer_moves(std::vector<PlacedMap>& maps, std::vector<Contribution>& contributors);
  RefusedMaps refused_;
  std::map<std::string, Contribution> fused_contributions_;  ///< per robot: the map version fused
  bool deferred_ = false;
  bool moves_held_ = false;
  bool step_held_ = false;   ///< the last build took no step of a move in steps, to publish grown maps first  ///< the last build fused no move, to publish grown maps first
  bool unchanged_ = false;
  std::vector<Contribution> last_contributors_;  ///< of the last version built
  Stages stages_;
  std::vector<std::shared_ptr<const HeldMap>> replaced_;  ///< maps the last build replaced
  std::optional<std::pair<std::uint64_t, std::uint64_t>> last_built_;  ///< version and hash the fusion last encoded
};

/// One pose per robot known to the registry.
std::vector<PoseOut> pose_outputs(const Registry& registry);

}  // namespace mapmerge::server
