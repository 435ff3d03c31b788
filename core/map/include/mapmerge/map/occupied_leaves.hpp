#pragma once
/// A map's occupied leaves as sorted keys: a small stand-in for its octree where only "is this
/// point occupied" and "where is occupied space" are asked (an overlap estimate between two
/// maps). ~8 B per occupied leaf, where an OctoMap spends ~57 B per node, free ones included.

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

class OccupiedLeaves {
 public:
  /// Read off the map's binary body (its tree is not built), or off its tree when it has no body.
  static OccupiedLeaves of(const HeldMap& map);
  static OccupiedLeaves of(const octomap::OcTree& tree);

  double resolution() const { return resolution_; }
  std::size_t size() const { return size_; }  ///< occupied leaves [count]
  /// Whether the point [m] lies in an occupied leaf.
  bool occupied(const Eigen::Vector3d& p) const;
  /// The centre [m] of leaf i (0 <= i < size()), the leaves taken depth by depth.
  Eigen::Vector3d centre(std::size_t i) const;

 private:
  friend class OccupiedLeavesWalk;
  static constexpr unsigned kLevels = 17;  ///< leaf depths 0 (the root) .. 16 (one voxel)
  void add(unsigned depth, std::uint32_t x, std::uint32_t y, std::uint32_t z);
  void finish();

  double resolution_ = 0.0;
  std::size_t size_ = 0;
  /// Per depth: the leaves' smallest-corner keys, packed x | y << 16 | z << 32, sorted.
  std::array<std::vector<std::uint64_t>, kLevels> by_depth_;
};

/// The share [0..1] of `source`'s occupied leaves (up to `samples` of them, evenly spread) that
/// fall, moved by T_target_source, within one target voxel of an occupied target leaf.
double estimate_overlap(const OccupiedLeaves& target, const OccupiedLeaves& source,
                        const Eigen::Matrix4d& T_target_source, std::size_t samples);

}  // namespace mapmerge
