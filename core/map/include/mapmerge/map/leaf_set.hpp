#pragma once
/// A map's occupied (or free) leaves as sorted keys: a small stand-in for its octree where only
/// "is this point occupied (free)" and "where is occupied space" are asked: an overlap estimate
/// between two maps, a hypothesis's free-space conflicts. 8 B per leaf, where an OctoMap spends
/// ~57 B per node.

#include <array>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <vector>

#include <Eigen/Core>

namespace octomap {
class OcTree;
}

namespace mapmerge {

class HeldMap;

enum class LeafState { kFree, kOccupied };

class LeafSet {
 public:
  /// The map's leaves in `state`, read off its binary body (its tree is not built), or off its
  /// tree when it has no body.
  static LeafSet of(const HeldMap& map, LeafState state);
  static LeafSet of(const octomap::OcTree& tree, LeafState state);

  double resolution() const { return resolution_; }
  std::size_t size() const { return size_; }  ///< leaves [count]
  std::size_t memory_usage() const { return size_ * sizeof(std::uint64_t); }  ///< [bytes]
  /// Whether the point [m] lies in one of the leaves.
  bool contains(const Eigen::Vector3d& p) const;
  /// The centre [m] of leaf i (0 <= i < size()), the leaves taken depth by depth.
  Eigen::Vector3d centre(std::size_t i) const;

 private:
  friend class LeafSetWalk;
  static constexpr unsigned kLevels = 17;  ///< leaf depths 0 (the root) .. 16 (one voxel)
  void add(unsigned depth, std::uint32_t x, std::uint32_t y, std::uint32_t z);
  void finish();

  double resolution_ = 0.0;
  std::size_t size_ = 0;
  /// Per depth: the Morton codes of the leaves' smallest-corner keys, sorted.
  std::array<std::vector<std::uint64_t>, kLevels> by_depth_;
};

/// The share [0..1] of `source`'s leaves (up to `samples` of them, evenly spread) that fall,
/// moved by T_target_source, within one target voxel of a `target` leaf: of two maps' occupied
/// leaves, how much of the source's occupied space the target shares.
double estimate_overlap(const LeafSet& target, const LeafSet& source,
                        const Eigen::Matrix4d& T_target_source, std::size_t samples);

}  // namespace mapmerge
