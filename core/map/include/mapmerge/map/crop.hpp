#pragma once
/// Cutting a part out of a map and moving it into another frame: how tests, benchmarks and the
/// demo make partial robot maps with a known ground-truth transform from one real map.

#include <memory>

#include <Eigen/Geometry>
#include <octomap/OcTree.h>

namespace mapmerge {

/// A transform from roll, pitch, yaw (radians) and a translation: T = [Rz(yaw)·Ry(pitch)·Rx(roll) | t].
Eigen::Isometry3d make_transform(double x, double y, double z, double roll, double pitch, double yaw);

/// The paper's T_R (Table 1) as a 4x4 matrix: translation [m] and angles [deg],
/// R = Rx(roll)·Ry(pitch)·Rz(yaw).
Eigen::Matrix4d paper_transform(double x, double y, double z, double roll_deg, double pitch_deg,
                                  double yaw_deg);

/// The leaves of `tree` (occupied and free, pruned leaves expanded to full resolution) whose
/// centres lie inside `box`, each centre p moved to T_out_in·p, in a new tree of the same
/// resolution and log-odds. Returns an empty tree when nothing lies inside the box.
std::unique_ptr<octomap::OcTree> crop_and_transform(const octomap::OcTree& tree,
                                                    const Eigen::AlignedBox3d& box,
                                                    const Eigen::Isometry3d& T_out_in);

/// The same map at `factor` times coarser resolution: a coarse voxel is occupied when any of its
/// voxels is, else free when any is free (log-odds of the deciding voxel). Throws
/// std::invalid_argument when factor < 1.
std::unique_ptr<octomap::OcTree> coarsen(const octomap::OcTree& tree, int factor);

/// The same map on a finer grid of `resolution` [m]: every voxel whose centre lies in a leaf
/// takes that leaf's log-odds (fuse_into() into an empty tree; pruned). The map's detail stays
/// that of its own resolution. Throws std::invalid_argument unless 0 < resolution <= the map's.
std::unique_ptr<octomap::OcTree> refine(const octomap::OcTree& tree, double resolution);

/// Number of occupied full-resolution voxels whose centres lie in `box`.
std::size_t count_occupied(const octomap::OcTree& tree, const Eigen::AlignedBox3d& box);

/// Two parts of `tree` cut along `axis` (0: x, 1: y, 2: z) that share `overlap` ([0..1]) of its
/// occupied full-resolution voxels, the paper's Table 1 overlap r: `first` is the map below the
/// upper cut, `second` the map above the lower cut; each box reaches 1 m beyond the map's other
/// bounds.
struct OverlapCut {
  Eigen::AlignedBox3d first, second;
};
OverlapCut overlap_cut(const octomap::OcTree& tree, int axis, double overlap);

}  // namespace mapmerge
