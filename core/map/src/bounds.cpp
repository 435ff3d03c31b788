#include "mapmerge/map/bounds.hpp"

#include <array>
#include <cstdint>

namespace mapmerge {
namespace {

constexpr unsigned kTreeDepth = 16;

/// The leaves' cubes as integer voxel bounds: [lo, hi) in key units at full depth.
class BoundsWalk {
 public:
  explicit BoundsWalk(const octomap::OcTree& tree) : tree_(tree) {}

  void visit(const octomap::OcTreeNode* node, std::array<std::uint32_t, 3> corner, std::uint32_t size) {
    if (found_ && inside(corner, size)) return;  // cannot widen the box
    if (!tree_.nodeHasChildren(node)) {
      for (int a = 0; a < 3; ++a) {
        if (!found_ || corner[a] < lo_[a]) lo_[a] = corner[a];
        if (!found_ || corner[a] + size > hi_[a]) hi_[a] = corner[a] + size;
      }
      found_ = true;
      return;
    }
    const std::uint32_t half = size / 2;
    for (unsigned i = 0; i < 8; ++i) {
      if (!tree_.nodeChildExists(node, i)) continue;
      const std::array<std::uint32_t, 3> child{corner[0] + ((i & 1U) != 0 ? half : 0),
                                               corner[1] + ((i & 2U) != 0 ? half : 0),
                                               corner[2] + ((i & 4U) != 0 ? half : 0)};
      visit(tree_.getNodeChild(node, i), child, half);  // depth <= 16: bounded recursion
    }
  }

  Eigen::AlignedBox3d box(double resolution) const {
    if (!found_) return Eigen::AlignedBox3d();
    constexpr double kCentre = 1U << (kTreeDepth - 1);  // key of the cell at the origin
    Eigen::AlignedBox3d b;
    for (int a = 0; a < 3; ++a) {
      b.min()[a] = (static_cast<double>(lo_[a]) - kCentre) * resolution;
      b.max()[a] = (static_cast<double>(hi_[a]) - kCentre) * resolution;
    }
    return b;
  }

 private:
  bool inside(const std::array<std::uint32_t, 3>& corner, std::uint32_t size) const {
    for (int a = 0; a < 3; ++a) {
      if (corner[a] < lo_[a] || corner[a] + size > hi_[a]) return false;
    }
    return true;
  }

  const octomap::OcTree& tree_;
  std::array<std::uint32_t, 3> lo_{}, hi_{};
  bool found_ = false;
};

}  // namespace

Eigen::AlignedBox3d leaf_bounds(const octomap::OcTree& tree) {
  BoundsWalk walk(tree);
  if (tree.getRoot() != nullptr) walk.visit(tree.getRoot(), {0, 0, 0}, 1U << kTreeDepth);
  return walk.box(tree.getResolution());
}

}  // namespace mapmerge
