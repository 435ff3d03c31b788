#pragma once
/// Incremental fusion of a fleet's maps into one global map.
///
/// Every robot's evidence is resampled onto the global grid exactly as fuse_into() places it,
/// but kept as an exact per-voxel sum (log-odds quantised to 1/4096, a 64-bit fixed-point sum
/// plus the number of robots that contributed): clamping happens only when the map is read out.
/// So a robot's contribution can be taken out again exactly, and changing one robot touches only
/// what changed: a grown map of the same pose adds the difference of its leaves, a new pose
/// or resolution takes the old contribution out and puts the new one in. The result does not
/// depend on the order in which robots were added, updated or removed.
///
/// Semantics (differs from fuse_maps(), which clamps after each map): a voxel's log-odds is
/// clamp(sum of all robots' evidence), unknown when no robot has evidence for it.

#include <cstddef>
#include <cstdint>
#include <initializer_list>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <octomap/OcTree.h>

#include "mapmerge/map/fusion.hpp"
#include "mapmerge/map/global_delta.hpp"
#include "mapmerge/map/held_map.hpp"
#include "mapmerge/map/provenance.hpp"

namespace mapmerge {

namespace detail {
class SumTree;
struct EncodedBlocks;
}

/// A robot's map placed in the global frame, named for provenance.
struct NamedMap {
  std::string name;
  const octomap::OcTree* map = nullptr;
  Eigen::Matrix4d T_global_map = Eigen::Matrix4d::Identity();
};

/// Which map has the strongest occupied evidence for each voxel of the global grid of
/// `resolution` [m] (resampled as fusion places it), and each map's frame under its name.
/// O(occupied leaves of all maps).
Provenance provenance_of(const std::vector<NamedMap>& maps, double resolution);

/// What GlobalFusion::set() did.
struct GlobalFuseResult {
  bool ok = false;
  std::string reason;          ///< why the map was refused (it is then out of the global map)
  bool incremental = false;    ///< only the changed leaves were fused (same pose, same resolution)
  bool from_bodies = false;    ///< ... found by diffing the two maps' binary bodies, not their trees
  std::size_t cubes = 0;       ///< source leaves (or changed leaf regions) placed on the grid
  double work = 0.0;           ///< fusion work of the map (FuseConfig::max_work's measure)
  std::size_t voxel_updates = 0;
  std::size_t block_updates = 0;
  double diff_s = 0.0;   ///< wall time finding what changed (the difference walk, a body's check)
  double place_s = 0.0;  ///< wall time placing the changed leaves on the global grid
  /// The map was fused by difference at the robot's fused pose, not at the one asked for, which
  /// moves none of its voxels by keep_pose_within or more (pose_of() says which pose is fused).
  bool kept_pose = false;
  /// A move in steps (set()'s `move_step`) is under way: part of the map is fused at its new pose
  /// and the rest still at its old one. set() with the same map and pose continues it.
  bool moving = false;
};

/// The fleet's global map, kept up to date one robot at a time. Not thread-safe: one owner.
class GlobalFusion {
 public:
  /// `resolution` [m] of the global grid; `config`: fuse_free, rigid_tolerance and max_work
  /// (per robot map) as in fuse_into(); `prune` is ignored (the output is always canonical).
  explicit GlobalFusion(double resolution, const FuseConfig& config = FuseConfig{});
  ~GlobalFusion();
  GlobalFusion(const GlobalFusion&) = delete;
  GlobalFusion& operator=(const GlobalFusion&) = delete;

  /// Puts `robot`'s map at `T_global_robot` into the global map, replacing what it contributed
  /// before. The map is held (shared, never modified) to compute the next update's difference.
  /// A refused map (not rigid, too much work, null) takes the robot out of the global map.
  /// When the held map and the new one both have a binary body (HeldMap::binary_body), a grown
  /// map's difference is read off the two bodies (one pass over bytes, several times faster than
  /// walking both trees, same result) and neither map's tree is built; a new pose or resolution
  /// needs the trees (HeldMap::tree builds them).
  ///
  /// `keep_pose_within` [m] (> 0): when the robot is fused at a pose T0 of the same resolution
  /// and T0 and `T_global_robot` put no point of its fused and new leaves (extent_of() and the
  /// difference's cubes) keep_pose_within or more apart, the new map is fused by its difference
  /// at T0 (GlobalFuseResult::kept_pose): a refinement's sub-voxel correction costs no whole
  /// re-fusion. The difference is found before the test; a larger move fuses the map whole.
  ///
  /// `move_step` (> 0): the same map at a new pose moves in steps of at most this many leaves
  /// (its body's depth-first order): each call takes the next leaves out at the old pose and puts
  /// them in at the new one (GlobalFuseResult::moving until the last). In between, every leaf of
  /// the map counts once, at one of the two poses, so each step leaves a whole global map, and a
  /// move of a large map does not hold back the updates of the others. A new map of the same grid
  /// sent to the pose the robot is moving to goes in at once by its difference, each changed part
  /// at the pose of the part of the map it is in (GlobalFuseResult::moving; this call takes no
  /// step), and the move goes on with the new map. A call with another pose, or a map that cannot
  /// be diffed, first finishes the move at once. Maps without a checked body move whole. A new map
  /// of the same grid whose pose moved too far to keep goes in by its difference at the fused pose
  /// (kept_pose), then moves in steps from the same call on.
  GlobalFuseResult set(const std::string& robot, std::shared_ptr<const HeldMap> map,
                       const Eigen::Matrix4d& T_global_robot, double keep_pose_within = 0.0,
                       std::size_t move_step = 0);
  /// The same for a decoded map; `binary_body`: the validated body it was decoded from
  /// (DecodeResult::binary_body), or null.
  GlobalFuseResult set(const std::string& robot, std::shared_ptr<const octomap::OcTree> map,
                       const Eigen::Matrix4d& T_global_robot,
                       std::shared_ptr<const std::vector<std::uint8_t>> binary_body = nullptr);
  /// Reads `map`'s leaves and their fusion work ahead of a set() of that map, so that set() only
  /// places them: e.g. while the map's pose is still being found. Only a map without a checked
  /// binary body gains: a map with only a tree has its octree walked here, not in set() (one
  /// map's leaves are kept, 12 B a leaf, until the set() of that map or the next stage()); a
  /// full (`.ot`) body has its work summed here and its leaves read off it by set(). A binary
  /// body is read in one pass over bytes anyway: for it this does nothing.
  void stage(std::shared_ptr<const HeldMap> map);
  /// Threads set() and encode() may work on at once (default: one per core, at most 4; 1: the
  /// calling thread only). The sums and the bytes do not depend on it.
  void set_threads(unsigned threads);
  unsigned threads() const { return threads_; }
  /// Takes `robot`'s contribution out (no-op for a robot not fused).
  void remove(const std::string& robot);

  /// Whether `robot` is fused with exactly this map and pose (nothing to do for set()); false
  /// while it moves in steps.
  bool holds(const std::string& robot, const HeldMap* map, const Eigen::Matrix4d& T) const;
  /// Whether `robot`'s move in steps is under way.
  bool moving(const std::string& robot) const;
  /// Whether set() can replace `robot`'s fused map by `map`'s difference (at the fused pose):
  /// the robot is fused with a map of `map`'s resolution, not finer than the global grid.
  bool fuses_by_difference(const std::string& robot, const HeldMap& map) const;
  /// The pose `robot` is fused with, or is moving to in steps (nullopt for a robot not fused).
  std::optional<Eigen::Matrix4d> pose_of(const std::string& robot) const;
  /// The map `robot` is fused with (null for a robot not fused).
  std::shared_ptr<const HeldMap> map_of(const std::string& robot) const;
  /// A box [m, robot frame] holding every leaf `robot` put evidence in (nullopt for a robot not
  /// fused): exact after a whole fusion, grown by each difference's cubes after that (a leaf
  /// that lost its evidence may still be inside). No walk of the map.
  std::optional<Eigen::AlignedBox3d> extent_of(const std::string& robot) const;
  /// Robots in the global map, sorted.
  std::vector<std::string> robots() const;
  double resolution() const { return resolution_; }
  bool empty() const;

  /// The global map as a `.bt` payload (OcTree::writeBinary's bytes: maximum-likelihood
  /// occupancy, pruned) and as the bare binary body of octomap_msgs/Octomap. One pass over the
  /// global map, which also prunes the internal sums (merges equal blocks, drops empty space).
  /// The bytes of every block (a subtree of 2^5 voxels a side) are kept, and a block none of
  /// whose voxels changed since the last encode() is copied, not walked: encoding after an
  /// update costs O(changed blocks + their count), plus copying the bytes. Eight or more changed
  /// blocks are written on up to threads() threads (disjoint subtrees; same bytes).
  ///
  /// `patches`: the blocks that changed since the previous encode(), which turn the tree decoded
  /// from that encoding into the one decoded from this (apply_block_patches); none after the
  /// first encoding, and none when they would cost the receiver about as much as the whole map.
  struct Encoded {
    std::vector<std::uint8_t> bt;    ///< header + body
    std::vector<std::uint8_t> body;  ///< body only (octomap_msgs binary)
    std::size_t nodes = 0;           ///< nodes of the encoded tree
    std::optional<std::vector<BlockPatch>> patches;
  };
  Encoded encode();

  /// The global map as an OcTree with the clamped log-odds (pruned). O(global map).
  std::unique_ptr<octomap::OcTree> tree() const;

  /// The robot with the strongest occupied evidence per voxel, and each robot's frame (named by
  /// robot id). O(occupied leaves of all robots).
  Provenance provenance() const;

  /// Bytes held by the global sums (not counting the robots' maps, which are shared).
  std::size_t memory_usage() const;

 private:
  /// stage()'s leaves, for set() of their map.
  struct StagedLeaves;
  struct Entry {
    std::shared_ptr<const HeldMap> map;
    Eigen::Matrix4d T_global_robot;
    Eigen::AlignedBox3d extent;  ///< extent_of()
    /// A move in steps: the map's leaves (and parts of leaves) before `boundary` in its body's
    /// depth-first order (a Morton code of the finest keys) are fused at T_to, the others still
    /// at T_global_robot. A boundary is a point of the grid's order, not a count of one map's
    /// leaves, so a new map takes the same boundary: each part of its difference goes in at the
    /// pose its place is fused at.
    std::optional<Eigen::Matrix4d> T_to;
    std::uint64_t boundary = 0;
    /// pose_of(): where the map is fused, or is moving to.
    const Eigen::Matrix4d& pose() const { return T_to ? *T_to : T_global_robot; }
  };
  /// A pose and the sign its evidence goes in with.
  struct Placement {
    const Eigen::Matrix4d* T;
    int sign;
  };
  /// Places the leaves of `map` (parts of leaves, cut at the ends) whose places in the body's
  /// depth-first order lie in [from, to) (Morton codes, Entry::boundary), at most `limit` of them,
  /// at each of `at`, walking the body only as far as needed. Returns where the placed leaves
  /// end (the end of the order when the walk reached the body's end). The map must have a body
  /// whole_body() takes.
  std::uint64_t add_leaves(const HeldMap& map, std::uint64_t from, std::uint64_t to, std::size_t limit,
                           std::initializer_list<Placement> at, GlobalFuseResult& stats);
  /// The next `step` leaves of a moving entry to their new pose; ends the move after the last.
  /// Adds its time to `stats.place_s` and sets `stats.moving`.
  void move_step(Entry& entry, std::size_t step, GlobalFuseResult& stats);
  enum class Difference { kPlaced, kRefused, kTooFar };
  /// A new `map` of a moving entry (same grid, both with bodies) by its difference: each part at
  /// the pose its place is fused at (either side of the boundary); the entry then holds `map`
  /// and moves on from the same boundary. kTooFar: no bodies to diff (nothing placed).
  Difference add_moving_difference(Entry& moving, std::shared_ptr<const HeldMap> map, GlobalFuseResult& stats);
  /// fuses_by_difference() for the robot's entry.
  bool same_grid(const Entry& fused, const HeldMap& map) const;
  /// add_full() of a map whose frame is the grid's (identity pose, the grid's resolution): its
  /// leaves added as they are. False (nothing done) for any other map.
  bool place_on_own_grid(const HeldMap& map, const Eigen::Matrix4d& T, int sign, GlobalFuseResult& stats,
                         Eigen::AlignedBox3d* extent, const StagedLeaves* staged);
  /// `body_checked`: the entry's binary body was just scanned whole (as in set()): not again.
  /// `extent`: grown by every cube placed (null: not kept). `staged`: the entry map's leaves,
  /// read by stage() (null: its full body or tree is walked).
  void add_full(const Entry& entry, int sign, GlobalFuseResult& stats, bool body_checked = false,
                Eigen::AlignedBox3d* extent = nullptr, const StagedLeaves* staged = nullptr);
  /// Places what changed from `before` to `after` at `after`'s pose, or at `before`'s when
  /// `keep_pose_within` > 0 and the poses are that close over the leaves (then `after` gets
  /// before's pose). kTooFar: the poses differ and are not that close (nothing placed).
  Difference add_difference(const Entry& before, Entry& after, double keep_pose_within, GlobalFuseResult& stats);

  /// The staged leaves of `map`, taken out (null when another map or none is staged).
  std::unique_ptr<StagedLeaves> take_staged(const HeldMap& map);

  double resolution_;
  FuseConfig config_;
  unsigned threads_ = 1;
  std::unique_ptr<detail::SumTree> sums_;
  std::unique_ptr<detail::EncodedBlocks> encoded_;  ///< the last encode()'s blocks
  std::map<std::string, Entry> robots_;
  std::unique_ptr<StagedLeaves> staged_;
};

}  // namespace mapmerge
