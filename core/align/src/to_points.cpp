#include <stdexcept>
#include <string>

#include "mapmerge/align/stages.hpp"
#include "mapmerge/map/held_map.hpp"

namespace mapmerge::align {
namespace {

/// Number of full-resolution voxels along one edge of a leaf of the given size.
std::size_t voxels_per_edge(double leaf_size, double resolution) {
  return static_cast<std::size_t>(leaf_size / resolution + 0.5);
}

/// Appends the full-resolution voxel centres of an occupied leaf of `size` at `centre` (a pruned
/// leaf is expanded into its voxels), refusing more than config.max_points in all.
void add_block(std::vector<OccupiedPoint>& out, const Eigen::Vector3f& centre, double size, float occupancy,
               double res, const ToPointsConfig& config) {
  const std::size_t n = voxels_per_edge(size, res);
  if (out.size() + n * n * n > config.max_points) {
    throw std::invalid_argument("map has more than " + std::to_string(config.max_points) +
                                " occupied voxels (points.max_points)");
  }
  if (n <= 1) {
    out.push_back({centre, occupancy});
    return;
  }
  const auto half = static_cast<float>(size / 2.0);
  const Eigen::Vector3f corner = centre.array() - half;
  const auto r = static_cast<float>(res);
  for (std::size_t i = 0; i < n; ++i)
    for (std::size_t j = 0; j < n; ++j)
      for (std::size_t k = 0; k < n; ++k)
        out.push_back({corner + Eigen::Vector3f((i + 0.5F) * r, (j + 0.5F) * r, (k + 0.5F) * r), occupancy});
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
    add_block(out_, Eigen::Vector3f(c.x(), c.y(), c.z()), size, occupancy, res_, config_);
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

std::vector<OccupiedPoint> to_points(const HeldMap& map, const ToPointsConfig& config) {
  if (!map.has_body()) return to_points(*map.tree(), config);
  std::vector<OccupiedPoint> points;
  const double res = map.resolution();
  if (map.binary_body()) {
    // A binary body's occupied leaves all stand for the tree's upper clamping bound.
    const auto occupancy = static_cast<float>(octomap::probability(map.occupied_log_odds()));
    if (occupancy < config.min_occupancy) return points;
    map.for_each_leaf([&](const BodyLeaf& leaf) {
      if (leaf.occupied) add_block(points, leaf.centre, leaf.size, occupancy, res, config);
    });
    return points;
  }
  // A full body's leaves keep their own log-odds (OcTreeNode::getOccupancy of each).
  map.for_each_leaf([&](const BodyLeaf& leaf) {
    if (!leaf.occupied) return;
    const auto occupancy = static_cast<float>(octomap::probability(leaf.log_odds));
    if (occupancy >= config.min_occupancy) add_block(points, leaf.centre, leaf.size, occupancy, res, config);
  });
  return points;
}

}  // namespace mapmerge::align
