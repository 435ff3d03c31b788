#include <stdexcept>
#include <string>

#include "mapmerge/align/stages.hpp"

namespace mapmerge::align {
namespace {

/// Number of full-resolution voxels along one edge of a leaf of the given size.
std::size_t voxels_per_edge(double leaf_size, double resolution) {
  return static_cast<std::size_t>(leaf_size / resolution + 0.5);
}

}  // namespace

std::vector<OccupiedPoint> to_points(const octomap::OcTree& tree, const ToPointsConfig& config) {
  const double res = tree.getResolution();
  std::vector<OccupiedPoint> points;
  points.reserve(tree.getNumLeafNodes());
  for (auto it = tree.begin_leafs(), end = tree.end_leafs(); it != end; ++it) {
    if (!tree.isNodeOccupied(*it)) continue;
    const auto occupancy = static_cast<float>(it->getOccupancy());
    if (occupancy < config.min_occupancy) continue;
    const octomap::point3d c = it.getCoordinate();
    const std::size_t n = voxels_per_edge(it.getSize(), res);
    if (points.size() + n * n * n > config.max_points) {
      throw std::invalid_argument("map has more than " + std::to_string(config.max_points) +
                                  " occupied voxels (points.max_points)");
    }
    if (n <= 1) {
      points.push_back({Eigen::Vector3f(c.x(), c.y(), c.z()), occupancy});
      continue;
    }
    // Pruned leaf: expand into its full-resolution voxels.
    const float half = static_cast<float>(it.getSize() / 2.0);
    const Eigen::Vector3f corner(c.x() - half, c.y() - half, c.z() - half);
    const auto r = static_cast<float>(res);
    for (std::size_t i = 0; i < n; ++i)
      for (std::size_t j = 0; j < n; ++j)
        for (std::size_t k = 0; k < n; ++k) {
          const Eigen::Vector3f offset((i + 0.5F) * r, (j + 0.5F) * r, (k + 0.5F) * r);
          points.push_back({corner + offset, occupancy});
        }
  }
  return points;
}

}  // namespace mapmerge::align
