#pragma once
/// Building test pairs from one real map (tests, bench, the paper's recipe): crop a box, move
/// it by a known rigid transform, coarsen. No PCL.

#include <memory>

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <octomap/OcTree.h>

namespace mapmerge::align {

/// The occupied and free voxels of `tree` whose centres lie in `box` (full resolution, log-odds
/// kept), each centre p moved to T * p. Where moved voxels collide, occupied wins.
std::unique_ptr<octomap::OcTree> cut_and_move(const octomap::OcTree& tree,
                                              const Eigen::AlignedBox3d& box,
                                              const Eigen::Matrix4d& T);

/// Same map at `factor` times coarser resolution: a coarse voxel is occupied when any of its
/// voxels is, else free when any is free.
std::unique_ptr<octomap::OcTree> coarsen(const octomap::OcTree& tree, int factor);

/// Number of occupied full-resolution voxels with centres in `box`.
std::size_t count_occupied(const octomap::OcTree& tree, const Eigen::AlignedBox3d& box);

/// Rigid transform from translation [m] and roll, pitch, yaw [deg] as R = Rx(roll) Ry(pitch) Rz(yaw)
/// (the convention of the paper's T_R).
Eigen::Matrix4d make_transform(double x, double y, double z, double roll_deg, double pitch_deg,
                               double yaw_deg);

}  // namespace mapmerge::align
