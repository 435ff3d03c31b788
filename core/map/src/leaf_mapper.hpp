#pragma once
/// Resampling of source leaves onto a target voxel grid (internal to mapmerge_core): shared by
/// fuse_into() and GlobalFusion so both place every leaf on exactly the same target voxels.

#include <algorithm>
#include <cmath>

#include <Eigen/Core>
#include <Eigen/LU>
#include <octomap/OcTree.h>

#include <string>

#include "mapmerge/map/fusion.hpp"
#include "tree_scan.hpp"

namespace mapmerge::detail {

constexpr int kKeyCentre = 32768;  ///< OctoMap's key of the voxel just above coordinate 0
constexpr int kKeyMax = 65535;

/// Places source leaves (oriented cubes once moved) onto the target's voxel grid: every aligned
/// target block whose voxel centres all lie in a cube goes to `sink.apply(key, level, delta)`
/// (level 0: one voxel). `Sink` decides what a delta is (log-odds, packed sums, votes).
template <typename Sink, typename Delta>
class LeafMapper {
 public:
  LeafMapper(const Eigen::Matrix4d& T_target_source, double target_res, Sink& sink, FuseResult& stats)
      : R_(T_target_source.topLeftCorner<3, 3>()),
        Rt_(R_.transpose()),
        t_(T_target_source.topRightCorner<3, 1>()),
        res_(target_res),
        abs_Rt_row_sum_(Rt_.cwiseAbs().rowwise().sum()),
        abs_R_row_sum_(R_.cwiseAbs().rowwise().sum()),
        sink_(sink),
        stats_(stats) {}

  /// Adds `delta` to every target voxel whose centre lies in the cube (centre `c`, edge `size`,
  /// source frame). Half-open bounds give each target voxel to exactly one source leaf.
  void add_cube(const Eigen::Vector3d& c, double size, Delta delta) {
    int lo[3];
    int hi[3];
    if (!key_bounds(c, size, lo, hi)) return;
    c_ = c;
    h_ = 0.5 * size;
    delta_ = delta;
    for (int i = 0; i < 3; ++i) {  // the window's part (everything unless set_window())
      lo[i] = std::max(lo[i], window_lo_[i]);
      hi[i] = std::min(hi[i], window_hi_[i]);
      if (lo[i] > hi[i]) return;
    }
    // Largest aligned target block that may fit inside the cube (and inside the window).
    unsigned level = 0;
    while (level < max_level_ && static_cast<double>(2U << level) * res_ <= size * (1 + 1e-9)) ++level;
    for (int x = lo[0] >> level; x <= hi[0] >> level; ++x) {
      for (int y = lo[1] >> level; y <= hi[1] >> level; ++y) {
        for (int z = lo[2] >> level; z <= hi[2] >> level; ++z) {
          visit(x << level, y << level, z << level, level);
        }
      }
    }
  }

  /// The target keys whose voxel centres may lie in the cube (centre `c`, edge `size`, source
  /// frame), clipped to the key space: false when none is left. Counts clipped leaves.
  bool key_bounds(const Eigen::Vector3d& c, double size, int lo[3], int hi[3]) {
    const Eigen::Vector3d ct = R_ * c + t_;
    const Eigen::Vector3d e = 0.5 * size * abs_R_row_sum_;
    bool clipped = false;
    for (int i = 0; i < 3; ++i) {
      lo[i] = static_cast<int>(std::ceil((ct[i] - e[i]) / res_ + (kKeyCentre - 0.5) - 1e-9));
      hi[i] = static_cast<int>(std::floor((ct[i] + e[i]) / res_ + (kKeyCentre - 0.5) + 1e-9));
      clipped |= lo[i] < 0 || hi[i] > kKeyMax;
      lo[i] = std::max(lo[i], 0);
      hi[i] = std::min(hi[i], kKeyMax);
      if (lo[i] > hi[i]) {
        ++stats_.leaves_clipped;
        return false;
      }
    }
    stats_.leaves_clipped += clipped;
    return true;
  }

  /// From now on add_cube() updates only the aligned block of 2^level voxels per side at
  /// `first` (its smallest key), in steps of at most that block: mappers of disjoint windows
  /// may run at once.
  void set_window(const octomap::OcTreeKey& first, unsigned level) {
    for (int i = 0; i < 3; ++i) {
      window_lo_[i] = first[i];
      window_hi_[i] = first[i] + (1 << level) - 1;
    }
    max_level_ = level;
  }

 private:
  /// The aligned block of 2^level voxels per side at key (x, y, z): update it whole when all its
  /// voxel centres are inside the cube, skip it when none can be, otherwise split it.
  void visit(int x, int y, int z, unsigned level) {
    if (x > kKeyMax || y > kKeyMax || z > kKeyMax) return;
    const double a = 0.5 * ((1 << level) - 1) * res_;  // centre-to-outer-voxel-centre offset
    const Eigen::Vector3d mid((x - kKeyCentre + 0.5) * res_ + a, (y - kKeyCentre + 0.5) * res_ + a,
                              (z - kKeyCentre + 0.5) * res_ + a);
    const Eigen::Vector3d p = Rt_ * (mid - t_) - c_;  // block middle in the leaf's frame
    const Eigen::Vector3d reach = a * abs_Rt_row_sum_;
    bool inside = true;
    for (int i = 0; i < 3; ++i) {
      if (p[i] + reach[i] < -h_ || p[i] - reach[i] >= h_) return;  // no centre can be inside
      inside &= p[i] - reach[i] >= -h_ && p[i] + reach[i] < h_;
    }
    if (inside) {
      apply(x, y, z, level);
      return;
    }
    if (level == 0) return;
    const int half = 1 << (level - 1);
    for (int i = 0; i < 8; ++i) {
      visit(x + (i & 1) * half, y + ((i >> 1) & 1) * half, z + ((i >> 2) & 1) * half, level - 1);
    }
  }

  void apply(int x, int y, int z, unsigned level) {
    const octomap::OcTreeKey key(static_cast<octomap::key_type>(x),
                                 static_cast<octomap::key_type>(y),
                                 static_cast<octomap::key_type>(z));
    sink_.apply(key, level, delta_);
    if (level == 0) {
      ++stats_.voxel_updates;
    } else {
      ++stats_.block_updates;
    }
  }

  Eigen::Matrix3d R_;
  Eigen::Matrix3d Rt_;
  Eigen::Vector3d t_;
  double res_;
  Eigen::Vector3d abs_Rt_row_sum_;
  Eigen::Vector3d abs_R_row_sum_;
  Sink& sink_;
  FuseResult& stats_;
  Eigen::Vector3d c_;
  double h_ = 0.0;
  Delta delta_{};
  int window_lo_[3] = {0, 0, 0};
  int window_hi_[3] = {kKeyMax, kKeyMax, kKeyMax};
  unsigned max_level_ = 15;
};

inline std::string check_rigid(const Eigen::Matrix4d& T, double tolerance) {
  if (!T.allFinite()) return "transform has non-finite entries";
  if (!T.row(3).isApprox(Eigen::RowVector4d(0, 0, 0, 1), tolerance)) {
    return "transform's last row is not (0, 0, 0, 1)";
  }
  const Eigen::Matrix3d R = T.topLeftCorner<3, 3>();
  if ((R.transpose() * R - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff() > tolerance ||
      R.determinant() < 0) {
    return "transform's rotation is not a proper rotation";
  }
  return "";
}

/// The target voxel visits fusing one leaf of `size` [m] costs (estimate_work's term).
inline double leaf_work(double size, bool occupied, double target_res, bool fuse_free) {
  if (!fuse_free && !occupied) return 0.0;
  return detail::leaf_fusion_work(std::max(1.0, std::ceil(size / target_res)));
}

/// Upper bound of the target voxel visits fusing `source` costs (see FuseConfig::max_work).
inline double estimate_work(const octomap::OcTree& source, double target_res, bool fuse_free) {
  double work = 0.0;
  for (auto it = source.begin_leafs(), end = source.end_leafs(); it != end; ++it) {
    work += leaf_work(it.getSize(), source.isNodeOccupied(*it), target_res, fuse_free);
  }
  return work;
}

}  // namespace mapmerge::detail
