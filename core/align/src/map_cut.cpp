#include "mapmerge/align/map_cut.hpp"

#include <cmath>
#include <stdexcept>

namespace mapmerge::align {
namespace {

/// Calls f(centre, log_odds, occupied) for every full-resolution voxel of the leaves meeting `box`.
template <class F>
void for_each_voxel(const octomap::OcTree& tree, const Eigen::AlignedBox3d& box, F&& f) {
  const double res = tree.getResolution();
  for (auto it = tree.begin_leafs(), end = tree.end_leafs(); it != end; ++it) {
    const double half = it.getSize() / 2.0;
    const octomap::point3d c = it.getCoordinate();
    const Eigen::Vector3d centre(c.x(), c.y(), c.z());
    const Eigen::AlignedBox3d leaf(centre.array() - half, centre.array() + half);
    if (!box.intersects(leaf)) continue;
    const bool occupied = tree.isNodeOccupied(*it);
    const float value = it->getLogOdds();
    const int n = static_cast<int>(it.getSize() / res + 0.5);
    const Eigen::Vector3d corner = leaf.min();
    for (int i = 0; i < n; ++i)
      for (int j = 0; j < n; ++j)
        for (int k = 0; k < n; ++k) {
          const Eigen::Vector3d p = corner + res * Eigen::Vector3d(i + 0.5, j + 0.5, k + 0.5);
          if (box.contains(p)) f(p, value, occupied);
        }
  }
}

std::unique_ptr<octomap::OcTree> empty_like(const octomap::OcTree& tree, double resolution) {
  auto out = std::make_unique<octomap::OcTree>(resolution);
  out->setClampingThresMin(tree.getClampingThresMin());
  out->setClampingThresMax(tree.getClampingThresMax());
  out->setOccupancyThres(tree.getOccupancyThres());
  return out;
}

}  // namespace

std::unique_ptr<octomap::OcTree> cut_and_move(const octomap::OcTree& tree,
                                              const Eigen::AlignedBox3d& box,
                                              const Eigen::Matrix4d& T) {
  auto out = empty_like(tree, tree.getResolution());
  const Eigen::Matrix3d R = T.topLeftCorner<3, 3>();
  const Eigen::Vector3d t = T.topRightCorner<3, 1>();
  auto put = [&](bool want_occupied) {
    for_each_voxel(tree, box, [&](const Eigen::Vector3d& p, float value, bool occupied) {
      if (occupied != want_occupied) return;
      const Eigen::Vector3d q = R * p + t;
      octomap::OcTreeKey key;
      if (!out->coordToKeyChecked(q.x(), q.y(), q.z(), key)) return;
      out->setNodeValue(key, value, true);
    });
  };
  put(false);  // free first: occupied voxels overwrite on collision
  put(true);
  out->updateInnerOccupancy();
  out->prune();
  return out;
}

std::unique_ptr<octomap::OcTree> coarsen(const octomap::OcTree& tree, int factor) {
  if (factor < 1) throw std::invalid_argument("coarsen: factor must be >= 1");
  auto out = empty_like(tree, tree.getResolution() * factor);
  const Eigen::AlignedBox3d all(Eigen::Vector3d::Constant(-1e9), Eigen::Vector3d::Constant(1e9));
  auto put = [&](bool want_occupied) {
    for_each_voxel(tree, all, [&](const Eigen::Vector3d& p, float value, bool occupied) {
      if (occupied != want_occupied) return;
      octomap::OcTreeKey key;
      if (!out->coordToKeyChecked(p.x(), p.y(), p.z(), key)) return;
      out->setNodeValue(key, value, true);
    });
  };
  put(false);
  put(true);
  out->updateInnerOccupancy();
  out->prune();
  return out;
}

std::size_t count_occupied(const octomap::OcTree& tree, const Eigen::AlignedBox3d& box) {
  std::size_t n = 0;
  for_each_voxel(tree, box, [&](const Eigen::Vector3d&, float, bool occupied) { n += occupied; });
  return n;
}

Eigen::Matrix4d make_transform(double x, double y, double z, double roll_deg, double pitch_deg,
                               double yaw_deg) {
  const double k = M_PI / 180.0;
  Eigen::Matrix4d T = Eigen::Matrix4d::Identity();
  T.topLeftCorner<3, 3>() = (Eigen::AngleAxisd(roll_deg * k, Eigen::Vector3d::UnitX()) *
                             Eigen::AngleAxisd(pitch_deg * k, Eigen::Vector3d::UnitY()) *
                             Eigen::AngleAxisd(yaw_deg * k, Eigen::Vector3d::UnitZ()))
                                .toRotationMatrix();
  T.topRightCorner<3, 1>() = Eigen::Vector3d(x, y, z);
  return T;
}

}  // namespace mapmerge::align
