#pragma once
/// The extent of an octree's leaves, and how far a box moves between two poses.

#include <Eigen/Geometry>
#include <octomap/OcTree.h>

#include "mapmerge/map/held_map.hpp"

namespace mapmerge {

/// The box [m] spanned by the leaves of `tree`, occupied and free, each leaf counted with its
/// whole cube: what OcTree::getMetricMin()/getMetricMax() report, but from one walk that skips
/// every subtree lying inside the box found so far (O(nodes near the box's faces) on real maps),
/// where OctoMap's const versions iterate over all leaves, once for each call. An empty box for
/// an empty tree.
Eigen::AlignedBox3d leaf_bounds(const octomap::OcTree& tree);

/// The same box for a held map, read off its body (binary or full) when its tree is not built
/// (one pass over the bytes; the tree is not built).
Eigen::AlignedBox3d leaf_bounds(const HeldMap& map);

/// The largest distance [m] between where `a` and where `b` (rigid 4x4 transforms) put a point
/// of `box`: the difference is affine in the point, so its largest norm is at a corner. 0 for an
/// empty box.
double max_displacement(const Eigen::Matrix4d& a, const Eigen::Matrix4d& b, const Eigen::AlignedBox3d& box);

}  // namespace mapmerge
