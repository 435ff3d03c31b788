#include <stdexcept>
#include <string>

#include "mapmerge/align/stages.hpp"

namespace mapmerge::align {
namespace {

/// Number of full-resolution voxels along one edge of a leaf of the given size.
std::size_t voxels_per_edge(double leaf_size, double resolution) {
  return static_cast<std::size_t>(leaf_size / resolution + 0.5);
}

/// Depth-first walk that skips subtrees whose inner node is free: an inner node holds the
/// largest log-odds of its children, so nothing below it is occupied.
class Collector {
 public:
  Collector(const octomap::OcTree& tree, const ToPointsConfig& config,
            std::vector<OccupiedPoint>& out)
      : tree_(tree), config_(config), out_(out), res_(tree.getResolution()) {}

  void visit(const octomap::OcTreeNode* node, const octomap::OcTreeKey& key, unsigned depth) {
    if (!tree_.isNodeOccupied(node)) return;
    if (tree_.nodeHasChildren(node)) {
      const octomap::key_type offset =
          static_cast<octomap::key_type>(tree_.getTreeDepth() > depth + 1
                                             ? 1U << (tree_.getTreeDepth() - depth - 2)
                                             : 0U);
      for (unsigned i = 0; i < 8; ++i) {
        if (!tree_.nodeChildExists(node, i)) continue;
        octomap::OcTreeKey child;
        octomap::computeChildKey(i, offset, key, child);
        visit(tree_.getNodeChild(node, i), child, depth + 1);
      }
      return;
    }
    add_leaf(node, key, depth);
  }

 private:
  void add_leaf(const octomap::OcTreeNode* node, const octomap::OcTreeKey& key, unsigned depth) {
    const auto occupancy = static_cast<float>(node->getOccupancy());
    if (occupancy < config_.min_occupancy) return;
    const double size = tree_.getNodeSize(depth);
    const octomap::point3d c = tree_.keyToCoord(key, depth);
    add_block(Eigen::Vector3f(c.x(), c.y(), c.z()), size, occupancy);
  }

  void add_block(const Eigen::Vector3f& centre, double size, float occupancy) {
    const std::size_t n = voxels_per_edge(size, res_);
    if (out_.size() + n * n * n > config_.max_points) {
      throw std::invalid_argument("map has more than " + std::to_string(config_.max_points) +
                                  " occupied voxels (points.max_points)");
    }
    if (n <= 1) {
      out_.push_back({centre, occupancy});
      return;
    }
    // Pruned leaf: expand into its full-resolution voxels.
    const auto half = static_cast<float>(size / 2.0);
    const Eigen::Vector3f corner = centre.array() - half;
    const auto r = static_cast<float>(res_);
    for (std::size_t i = 0; i < n; ++i)
      for (std::size_t j = 0; j < n; ++j)
        for (std::size_t k = 0; k < n; ++k)
          out_.push_back({corner + Eigen::Vector3f((i + 0.5F) * r, (j + 0.5F) * r, (k + 0.5F) * r),
                          occupancy});
  }

  const octomap::OcTree& tree_;
  const ToPointsConfig& config_;
  std::vector<OccupiedPoint>& out_;
  double res_;
};

}  // namespace

std::vector<OccupiedPoint> to_points(const octomap::OcTree& tree, const ToPointsConfig& config) {
  std::vector<OccupiedPoint> points;
  if (tree.getRoot() == nullptr) return points;
  const auto centre = static_cast<octomap::key_type>(1U << (tree.getTreeDepth() - 1));
  Collector(tree, config, points).visit(tree.getRoot(), octomap::OcTreeKey(centre, centre, centre), 0);
  return points;
}

}  // namespace mapmerge::align
