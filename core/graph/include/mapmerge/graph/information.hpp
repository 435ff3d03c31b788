#pragma once
/// Information matrix of one pairwise alignment (issue 8), from the quality numbers the
/// alignment pipeline reports (mapmerge::align::AlignResult: inliers, fitness, overlap).
///
/// Convention used by the whole pose graph: the error of an edge is the 6-vector
/// [rho (m); phi (rad)] of E = T_target_source_measured^-1 * T_target_source_true, expressed in
/// the source frame at the source origin (first-order SE(3) log: translation first).
///
/// Noise model (documented proxy, not a fitted covariance):
///   sigma_t = max(fitness, min_fitness)
///             * sqrt(reference_inliers / clamp(inliers, 1, max_inlier_gain * reference_inliers))
///             * sqrt(reference_overlap / clamp(overlap, min_overlap, reference_overlap))   [m]
///   sigma_r = sigma_t / lever_arm                                                          [rad]
/// i.e. an alignment with `reference_inliers` inliers and enough overlap is trusted to about its
/// own mean inlier distance; more inliers help with diminishing returns (errors of neighbouring
/// voxels are correlated), little overlap hurts. The noise is isotropic *at the pivot* (centre of
/// the overlap region, source frame): a rotation error there moves the source origin by
/// phi x (origin - pivot), so the matrix at the origin couples rotation and translation.

#include <string>

#include <Eigen/Core>
#include <Eigen/Geometry>

namespace mapmerge::graph {

using Matrix6d = Eigen::Matrix<double, 6, 6>;

/// Settings of information_from_alignment.
struct InformationConfig {
  double min_fitness = 0.01;          ///< floor on the fitness used as point noise: a perfect fit is not a perfect pose [m]
  double reference_inliers = 2000.0;  ///< inlier count at which sigma_t equals the fitness [count]
  double max_inlier_gain = 4.0;       ///< inliers count at most this many times reference_inliers [ratio]
  double reference_overlap = 0.3;     ///< overlap at or above which no penalty applies [0..1]
  double min_overlap = 0.02;          ///< floor on the overlap used in the penalty [0..1]
  double lever_arm = 3.0;             ///< typical distance of the inliers from their centroid; sigma_r = sigma_t / lever_arm [m]
};

/// Quality of one accepted alignment, as reported by the alignment pipeline.
struct AlignmentQuality {
  std::size_t inliers = 0;     ///< pairs closer than the inlier distance [count]
  double fitness = 0.0;        ///< mean inlier distance (Eq. 6 of the paper) [m]
  double overlap = 0.0;        ///< share of points seen by both maps [0..1]
  Eigen::Vector3d pivot_source = Eigen::Vector3d::Zero();  ///< centre of the overlap region in the source frame [m]; zero = source origin
};

struct EdgeInformation {
  bool valid = false;            ///< false: inputs unusable (no inliers, non-finite fitness, ...); see reason
  Matrix6d information = Matrix6d::Zero();  ///< inverse covariance of [rho (m); phi (rad)] at the source origin
  double sigma_translation = 0.0;  ///< sigma_t at the pivot [m]
  double sigma_rotation = 0.0;     ///< sigma_r [rad]
  std::string reason;            ///< why not valid (empty when valid)
};

/// Information matrix of an alignment edge from its quality numbers (model above). Never throws.
EdgeInformation information_from_alignment(const AlignmentQuality& quality,
                                           const InformationConfig& config = {});

/// Information of an isotropic noise of sigma_translation [m] and sigma_rotation [rad] acting at
/// pivot_source (source frame), expressed at the source origin. Used by
/// information_from_alignment; handy in tests and simulations. Requires sigmas > 0.
Matrix6d information_at_pivot(double sigma_translation, double sigma_rotation,
                              const Eigen::Vector3d& pivot_source);

/// A pivot for AlignmentQuality when the aligner does not report the inliers' centroid: the
/// centre of the overlap of the two maps' bounding boxes, in the source frame (the target's box
/// moved into the source frame by T_target_source^-1, as an axis-aligned box). Falls back to the
/// centre of the source box when the boxes do not overlap or a box is empty.
Eigen::Vector3d overlap_pivot(const Eigen::AlignedBox3d& source_box,
                              const Eigen::AlignedBox3d& target_box,
                              const Eigen::Isometry3d& T_target_source);

}  // namespace mapmerge::graph
