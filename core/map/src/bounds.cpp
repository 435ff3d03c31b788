#include "mapmerge/map/bounds.hpp"

#include <algorithm>
#include <array>
#include <cstdint>

#include "body_leaves.hpp"

namespace mapmerge {
namespace {

using detail::kTreeDepth;

/// The leaves' cubes as integer voxel bounds: [lo, hi) in key units at full depth.
class BoundsWalk {
 public:
  void visit(const octomap::OcTree& tree, const octomap::OcTreeNode* node, std::array<std::uint32_t, 3> corner,
             std::uint32_t size) {
    if (found_ && inside(corner, size)) return;  // cannot widen the box
    if (!tree.nodeHasChildren(node)) {
      add_leaf(corner, size);
      return;
    }
    const std::uint32_t half = size / 2;
    for (unsigned i = 0; i < 8; ++i) {
      if (!tree.nodeChildExists(node, i)) continue;
      visit(tree, tree.getNodeChild(node, i), child_corner(corner, half, i), half);  // depth <= 16
    }
  }

  /// A leaf of a binary body (every byte is read: a subtree's length is known only by reading it).
  void leaf(std::array<std::uint32_t, 3> corner, std::uint32_t size) {
    if (!found_ || !inside(corner, size)) add_leaf(corner, size);
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
  static std::array<std::uint32_t, 3> child_corner(const std::array<std::uint32_t, 3>& corner, std::uint32_t half,
                                                   unsigned i) {
    return {corner[0] + ((i & 1U) != 0 ? half : 0), corner[1] + ((i & 2U) != 0 ? half : 0),
            corner[2] + ((i & 4U) != 0 ? half : 0)};
  }

  void add_leaf(const std::array<std::uint32_t, 3>& corner, std::uint32_t size) {
    for (int a = 0; a < 3; ++a) {
      if (!found_ || corner[a] < lo_[a]) lo_[a] = corner[a];
      if (!found_ || corner[a] + size > hi_[a]) hi_[a] = corner[a] + size;
    }
    found_ = true;
  }

  bool inside(const std::array<std::uint32_t, 3>& corner, std::uint32_t size) const {
    for (int a = 0; a < 3; ++a) {
      if (corner[a] < lo_[a] || corner[a] + size > hi_[a]) return false;
    }
    return true;
  }

  std::array<std::uint32_t, 3> lo_{}, hi_{};
  bool found_ = false;
};

}  // namespace

Eigen::AlignedBox3d leaf_bounds(const octomap::OcTree& tree) {
  BoundsWalk walk;
  if (tree.getRoot() != nullptr) walk.visit(tree, tree.getRoot(), {0, 0, 0}, 1U << kTreeDepth);
  return walk.box(tree.getResolution());
}

Eigen::AlignedBox3d leaf_bounds(const HeldMap& map) {
  if (map.has_tree() || !map.has_body()) return leaf_bounds(*map.tree());
  BoundsWalk walk;
  detail::for_each_body_leaf(map, [&](float, bool, unsigned depth, std::uint32_t x, std::uint32_t y, std::uint32_t z) {
    walk.leaf({x, y, z}, (1U << kTreeDepth) >> depth);
  });
  return walk.box(map.resolution());
}

double max_displacement(const Eigen::Matrix4d& a, const Eigen::Matrix4d& b, const Eigen::AlignedBox3d& box) {
  if (box.isEmpty()) return 0.0;
  const Eigen::Matrix4d d = b - a;
  double worst = 0.0;
  for (int i = 0; i < 8; ++i) {
    const Eigen::Vector3d p = box.corner(static_cast<Eigen::AlignedBox3d::CornerType>(i));
    worst = std::max(worst, (d.topLeftCorner<3, 3>() * p + d.topRightCorner<3, 1>()).norm());
  }
  return worst;
}

}  // namespace mapmerge
