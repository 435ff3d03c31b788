#include "mapmerge/graph/information.hpp"

#include <algorithm>
#include <cmath>

#include "work_graph.hpp"

namespace mapmerge::graph {

Matrix6d information_at_pivot(double sigma_translation, double sigma_rotation,
                              const Eigen::Vector3d& pivot_source) {
  // Noise nu = [rho; phi] at the pivot moves the origin by Ad(translate(pivot)) nu.
  Matrix6d A = Matrix6d::Identity();
  A.topRightCorner<3, 3>() = detail::skew(pivot_source);
  Matrix6d sigma_pivot = Matrix6d::Zero();
  sigma_pivot.topLeftCorner<3, 3>().diagonal().setConstant(sigma_translation * sigma_translation);
  sigma_pivot.bottomRightCorner<3, 3>().diagonal().setConstant(sigma_rotation * sigma_rotation);
  // (A S A^T)^-1 = A^-T S^-1 A^-1, with A^-1 = I - (A - I).
  Matrix6d A_inv = Matrix6d::Identity();
  A_inv.topRightCorner<3, 3>() = -detail::skew(pivot_source);
  Matrix6d info_pivot = Matrix6d::Zero();
  info_pivot.diagonal() << Eigen::Vector3d::Constant(1.0 / (sigma_translation * sigma_translation)),
      Eigen::Vector3d::Constant(1.0 / (sigma_rotation * sigma_rotation));
  Matrix6d info = A_inv.transpose() * info_pivot * A_inv;
  return 0.5 * (info + info.transpose());
}

namespace {

std::string check_quality(const AlignmentQuality& q, const InformationConfig& c) {
  if (q.inliers == 0) return "no inliers";
  if (!std::isfinite(q.fitness) || q.fitness < 0.0) return "fitness not finite and >= 0";
  if (!std::isfinite(q.overlap) || q.overlap < 0.0) return "overlap not finite and >= 0";
  if (!q.pivot_source.allFinite()) return "pivot not finite";
  if (!(c.min_fitness > 0.0) || !(c.reference_inliers > 0.0) || !(c.max_inlier_gain >= 1.0) ||
      !(c.reference_overlap > 0.0) || !(c.min_overlap > 0.0) || !(c.lever_arm > 0.0))
    return "bad InformationConfig (every scale must be > 0, max_inlier_gain >= 1)";
  return {};
}

}  // namespace

EdgeInformation information_from_alignment(const AlignmentQuality& quality,
                                           const InformationConfig& config) {
  EdgeInformation out;
  out.reason = check_quality(quality, config);
  if (!out.reason.empty()) return out;

  const double noise = std::max(quality.fitness, config.min_fitness);
  const double inliers = std::clamp(static_cast<double>(quality.inliers), 1.0,
                                    config.max_inlier_gain * config.reference_inliers);
  const double min_overlap = std::min(config.min_overlap, config.reference_overlap);
  const double overlap = std::clamp(quality.overlap, min_overlap, config.reference_overlap);
  out.sigma_translation = noise * std::sqrt(config.reference_inliers / inliers) *
                          std::sqrt(config.reference_overlap / overlap);
  out.sigma_rotation = out.sigma_translation / config.lever_arm;
  out.information =
      information_at_pivot(out.sigma_translation, out.sigma_rotation, quality.pivot_source);
  out.valid = out.information.allFinite();
  if (!out.valid) out.reason = "information not finite";
  return out;
}

Eigen::Vector3d overlap_pivot(const Eigen::AlignedBox3d& source_box,
                              const Eigen::AlignedBox3d& target_box,
                              const Eigen::Isometry3d& T_target_source) {
  if (source_box.isEmpty()) return Eigen::Vector3d::Zero();
  if (target_box.isEmpty()) return source_box.center();
  const Eigen::Isometry3d T_source_target = T_target_source.inverse();
  Eigen::AlignedBox3d target_in_source;
  for (int corner = 0; corner < 8; ++corner)
    target_in_source.extend(T_source_target * target_box.corner(static_cast<Eigen::AlignedBox3d::CornerType>(corner)));
  const Eigen::AlignedBox3d shared = source_box.intersection(target_in_source);
  return shared.isEmpty() ? source_box.center() : shared.center();
}

}  // namespace mapmerge::graph
