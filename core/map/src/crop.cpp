#include "mapmerge/map/crop.hpp"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <vector>

#include "mapmerge/map/bounds.hpp"
#include "mapmerge/map/fusion.hpp"

namespace mapmerge {

Eigen::Isometry3d make_transform(double x, double y, double z, double roll, double pitch, double yaw) {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = (Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ()) *
                Eigen::AngleAxisd(pitch, Eigen::Vector3d::UnitY()) *
                Eigen::AngleAxisd(roll, Eigen::Vector3d::UnitX()))
                   .toRotationMatrix();
  T.translation() = Eigen::Vector3d(x, y, z);
  return T;
}

Eigen::Matrix4d paper_transform(double x, double y, double z, double roll_deg, double pitch_deg,
                                  double yaw_deg) {
  const double k = M_PI / 180.0;
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = (Eigen::AngleAxisd(roll_deg * k, Eigen::Vector3d::UnitX()) *
                Eigen::AngleAxisd(pitch_deg * k, Eigen::Vector3d::UnitY()) *
                Eigen::AngleAxisd(yaw_deg * k, Eigen::Vector3d::UnitZ()))
                   .toRotationMatrix();
  T.translation() = Eigen::Vector3d(x, y, z);
  return T.matrix();
}

namespace {

/// Calls f(centre, log_odds, occupied) for every full-resolution voxel centre of `tree` in `box`.
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
    for (int i = 0; i < n; ++i)
      for (int j = 0; j < n; ++j)
        for (int k = 0; k < n; ++k) {
          const Eigen::Vector3d p = leaf.min() + res * Eigen::Vector3d(i + 0.5, j + 0.5, k + 0.5);
          if (box.contains(p)) f(p, value, occupied);
        }
  }
}

/// Sets every output cell whose centre maps back (T_in_out) into the input voxel `key_in`:
/// nearest-cell resampling, so a rotated map has neither holes nor thickened surfaces.
void resample_voxel(const octomap::OcTree& in, octomap::OcTree& out, const octomap::OcTreeKey& key_in,
                    const Eigen::Vector3d& p_in, const Eigen::Isometry3d& T_out_in,
                    const Eigen::Isometry3d& T_in_out, float value) {
  const Eigen::Vector3d q = T_out_in * p_in;
  octomap::OcTreeKey centre;
  if (!out.coordToKeyChecked(q.x(), q.y(), q.z(), centre)) return;
  for (int dx = -1; dx <= 1; ++dx) {
    for (int dy = -1; dy <= 1; ++dy) {
      for (int dz = -1; dz <= 1; ++dz) {
        const octomap::OcTreeKey k(static_cast<octomap::key_type>(centre[0] + dx),
                                   static_cast<octomap::key_type>(centre[1] + dy),
                                   static_cast<octomap::key_type>(centre[2] + dz));
        const octomap::point3d c = out.keyToCoord(k);
        const Eigen::Vector3d back = T_in_out * Eigen::Vector3d(c.x(), c.y(), c.z());
        octomap::OcTreeKey key_back;
        if (in.coordToKeyChecked(back.x(), back.y(), back.z(), key_back) && key_back == key_in) {
          out.setNodeValue(k, value, /*lazy_eval=*/true);
        }
      }
    }
  }
}

}  // namespace

std::unique_ptr<octomap::OcTree> crop_and_transform(const octomap::OcTree& tree,
                                                    const Eigen::AlignedBox3d& box,
                                                    const Eigen::Isometry3d& T_out_in) {
  const double res = tree.getResolution();
  auto out = std::make_unique<octomap::OcTree>(res);
  out->setClampingThresMin(tree.getClampingThresMin());
  out->setClampingThresMax(tree.getClampingThresMax());
  out->setOccupancyThres(tree.getOccupancyThres());
  const Eigen::Isometry3d T_in_out = T_out_in.inverse();
  // The leaf iterator needs a box inside the tree's key range: clamp to the map's extent.
  const Eigen::AlignedBox3d inside = box.intersection(leaf_bounds(tree));
  if (tree.size() == 0 || inside.isEmpty()) return out;
  const octomap::point3d bmin(static_cast<float>(inside.min().x()), static_cast<float>(inside.min().y()),
                              static_cast<float>(inside.min().z()));
  const octomap::point3d bmax(static_cast<float>(inside.max().x()), static_cast<float>(inside.max().y()),
                              static_cast<float>(inside.max().z()));
  for (auto it = tree.begin_leafs_bbx(bmin, bmax), end = tree.end_leafs_bbx(); it != end; ++it) {
    const float value = it->getLogOdds();
    const double size = it.getSize();
    const int cells = static_cast<int>(size / res + 0.5);
    const octomap::point3d c = it.getCoordinate();
    const double first = -0.5 * size + 0.5 * res;
    for (int i = 0; i < cells; ++i) {
      for (int j = 0; j < cells; ++j) {
        for (int k = 0; k < cells; ++k) {
          const Eigen::Vector3d p(c.x() + first + i * res, c.y() + first + j * res, c.z() + first + k * res);
          if (!box.contains(p)) continue;
          const octomap::OcTreeKey key_in = tree.coordToKey(p.x(), p.y(), p.z());
          resample_voxel(tree, *out, key_in, p, T_out_in, T_in_out, value);
        }
      }
    }
  }
  out->updateInnerOccupancy();
  out->prune();
  return out;
}

std::unique_ptr<octomap::OcTree> coarsen(const octomap::OcTree& tree, int factor) {
  if (factor < 1) throw std::invalid_argument("coarsen: factor must be >= 1");
  const double res = tree.getResolution();
  auto out = std::make_unique<octomap::OcTree>(res * factor);
  out->setClampingThresMin(tree.getClampingThresMin());
  out->setClampingThresMax(tree.getClampingThresMax());
  out->setOccupancyThres(tree.getOccupancyThres());
  // A leaf's full-resolution centres form a lattice; along each axis the coarse keys they fall
  // in are one run of keys, so the coarse voxels the leaf decides are the product of three
  // runs. A large pruned leaf then costs its coarse voxels, not factor^3 times as many fine
  // ones. Same result as setting the coarse voxel of every fine centre, leaf by leaf.
  for (const bool want_occupied : {false, true}) {  // occupied last: it wins a coarse voxel
    for (auto it = tree.begin_leafs(), end = tree.end_leafs(); it != end; ++it) {
      if (tree.isNodeOccupied(*it) != want_occupied) continue;
      const float value = it->getLogOdds();
      const double from_centre = it.getSize() / 2.0 - 0.5 * res;  // to the leaf's outer fine centres
      const octomap::point3d c = it.getCoordinate();
      octomap::OcTreeKey lo, hi;
      bool inside = true;
      for (unsigned a = 0; a < 3; ++a) {
        inside = inside && out->coordToKeyChecked(c(a) - from_centre, lo[a]) &&
                 out->coordToKeyChecked(c(a) + from_centre, hi[a]);
      }
      if (!inside) continue;  // beyond the coarse tree's key range
      for (unsigned x = lo[0]; x <= hi[0]; ++x)
        for (unsigned y = lo[1]; y <= hi[1]; ++y)
          for (unsigned z = lo[2]; z <= hi[2]; ++z) {
            const octomap::OcTreeKey k(static_cast<octomap::key_type>(x), static_cast<octomap::key_type>(y),
                                       static_cast<octomap::key_type>(z));
            out->setNodeValue(k, value, /*lazy_eval=*/true);
          }
    }
  }
  out->updateInnerOccupancy();
  out->prune();
  return out;
}

std::unique_ptr<octomap::OcTree> refine(const octomap::OcTree& tree, double resolution) {
  if (!(resolution > 0.0) || resolution > tree.getResolution() * (1 + 1e-9))
    throw std::invalid_argument("refine: resolution must be positive and at most the map's");
  auto out = std::make_unique<octomap::OcTree>(resolution);
  out->setClampingThresMin(tree.getClampingThresMin());
  out->setClampingThresMax(tree.getClampingThresMax());
  out->setOccupancyThres(tree.getOccupancyThres());
  const FuseResult r = fuse_into(*out, tree, Eigen::Matrix4d::Identity(), FuseConfig{});
  if (!r.ok) throw std::invalid_argument("refine: " + r.reason);
  return out;
}

std::size_t count_occupied(const octomap::OcTree& tree, const Eigen::AlignedBox3d& box) {
  std::size_t n = 0;
  for_each_voxel(tree, box, [&](const Eigen::Vector3d&, float, bool occupied) { n += occupied ? 1 : 0; });
  return n;
}

OverlapCut overlap_cut(const octomap::OcTree& tree, int axis, double overlap) {
  if (axis < 0 || axis > 2) throw std::invalid_argument("overlap_cut: axis must be 0, 1 or 2");
  if (!(overlap >= 0.0 && overlap <= 1.0)) throw std::invalid_argument("overlap_cut: overlap must be in [0, 1]");
  std::vector<double> coords;  // the axis coordinate of every occupied voxel
  const double res = tree.getResolution();
  for (auto it = tree.begin_leafs(); it != tree.end_leafs(); ++it) {
    if (!tree.isNodeOccupied(*it)) continue;
    const int n = static_cast<int>(it.getSize() / res + 0.5);
    const double c = it.getCoordinate()(axis);
    for (int i = 0; i < n; ++i)
      coords.insert(coords.end(), static_cast<std::size_t>(n * n), c - it.getSize() / 2 + res * (i + 0.5));
  }
  if (coords.empty()) throw std::invalid_argument("overlap_cut: the map has no occupied voxel");
  std::sort(coords.begin(), coords.end());
  auto at = [&](double q) { return coords[static_cast<std::size_t>(q * static_cast<double>(coords.size() - 1))]; };
  double lo[3], hi[3];
  tree.getMetricMin(lo[0], lo[1], lo[2]);
  tree.getMetricMax(hi[0], hi[1], hi[2]);
  OverlapCut cut;
  cut.first = Eigen::AlignedBox3d(Eigen::Vector3d(lo[0], lo[1], lo[2]) - Eigen::Vector3d::Constant(1),
                                  Eigen::Vector3d(hi[0], hi[1], hi[2]) + Eigen::Vector3d::Constant(1));
  cut.second = cut.first;
  cut.first.max()(axis) = at((1.0 + overlap) / 2.0);
  cut.second.min()(axis) = at((1.0 - overlap) / 2.0);
  return cut;
}

}  // namespace mapmerge
