#pragma once
/// Internal: what a PreparedMap holds. PCL types stay in this header and the *_pcl.cpp files.

#include <algorithm>
#include <cmath>
#include <memory>
#include <vector>

#include <pcl/point_cloud.h>
#include <pcl/point_types.h>

#include "mapmerge/align/align.hpp"
#include "mapmerge/map/leaf_set.hpp"
#include "serial_kd_tree.hpp"

namespace mapmerge::align {

using Point = pcl::PointXYZINormal;  ///< position, intensity = occupancy probability, normal
using Cloud = pcl::PointCloud<Point>;
/// A stage-1 voxel as held for validation and ICP's source: no normal (32 B a point, not 48;
/// the full-resolution points are the largest part of a prepared map).
using FullPoint = pcl::PointXYZI;
using FullCloud = pcl::PointCloud<FullPoint>;
using Fpfh = pcl::FPFHSignature33;
using Shot = pcl::SHOT352;

struct PreparedMap::Impl {
  double resolution = 0.0;
  std::shared_ptr<const LeafSet> free_space;    ///< the map's free leaves: validation's conflicts
  std::size_t num_points = 0;                   ///< occupied voxels of stage 1
  FullCloud::Ptr full;                           ///< stage 1 at full resolution (validation, ICP's source)
  SerialKdTree<FullPoint>::Ptr full_tree;        ///< kd-tree over `full`
  Cloud::Ptr cloud;                              ///< stage 2 output, with occupancy (and broad normals when prepared with features)
  Cloud::Ptr coarse;                             ///< `cloud` at the describe voxel: keypoints, descriptors
  Cloud::Ptr keypoints;                          ///< stage 4, only those with a valid descriptor
  pcl::PointCloud<Fpfh>::Ptr fpfh;               ///< stage 5 when FPFH (one per keypoint)
  pcl::PointCloud<Shot>::Ptr shot;               ///< stage 5 when SHOT
  SerialKdTree<Fpfh>::Ptr fpfh_tree;
  SerialKdTree<Shot>::Ptr shot_tree;
  StageTimings timings;
};

/// Normals of `cloud` from its neighbours within `radius` [m] (found with `search`, a kd-tree
/// over `cloud`), in parallel blocks. With `orient_to` (the map's free leaves), each faces the
/// map's free space (descriptors need a consistent sign; point-to-plane ICP does not). A point
/// with fewer than 3 neighbours gets +z; one whose neighbours are collinear keeps a NaN normal.
void estimate_normals(Cloud& cloud, const SerialKdTree<Point>& search, double radius, const LeafSet* orient_to,
                      double res);

/// A copy of `m` (stages 1-2 shared, not copied) with stages 4-5 computed anew under `config`:
/// the denser features of AlignConfig::rescue. `m` must have been prepared with features.
std::shared_ptr<const PreparedMap::Impl> with_features(const PreparedMap::Impl& m, const AlignConfig& config);

/// A hypothesis of stage 6 with its correspondence consensus.
struct Hypothesis {
  Eigen::Matrix4d T_target_source = Eigen::Matrix4d::Identity();
  std::size_t consensus = 0;  ///< correspondences agreeing [count]
  int submodel = -1;
};

/// Stage 6 correspondences: source keypoint index -> target keypoint index.
struct Match {
  int source = 0;
  int target = 0;
  float distance = 0.0F;  ///< descriptor distance (squared L2)
};

/// Stage 6a: descriptor correspondences between all source and target keypoints.
std::vector<Match> match_descriptors(const PreparedMap::Impl& target,
                                     const PreparedMap::Impl& source, const MatchConfig& config);

/// Stage 6b: hypotheses from the correspondences whose source keypoint is in `subset`
/// (indices into source keypoints), with the configured method.
std::vector<Hypothesis> generate_hypotheses(const PreparedMap::Impl& target,
                                            const PreparedMap::Impl& source,
                                            const std::vector<Match>& matches,
                                            const std::vector<int>& subset,
                                            const AlignConfig& config, unsigned seed);

}  // namespace mapmerge::align

namespace mapmerge::align {

/// Rotation angle between two transforms [deg].
inline double rotation_difference_deg(const Eigen::Matrix4d& a, const Eigen::Matrix4d& b) {
  const Eigen::Matrix3d r = a.topLeftCorner<3, 3>().transpose() * b.topLeftCorner<3, 3>();
  const double c = std::clamp((r.trace() - 1.0) / 2.0, -1.0, 1.0);
  return std::acos(c) * 180.0 / M_PI;
}

/// True when the transforms differ by less than the given rotation [deg] and translation [m].
inline bool same_pose(const Eigen::Matrix4d& a, const Eigen::Matrix4d& b, double rot_deg,
                      double trans) {
  return rotation_difference_deg(a, b) < rot_deg &&
         (a.topRightCorner<3, 1>() - b.topRightCorner<3, 1>()).norm() < trans;
}

}  // namespace mapmerge::align
