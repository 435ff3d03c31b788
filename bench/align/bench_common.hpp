#pragma once
// What the alignment benches share: the errors of an estimate against the truth, the success
// bounds, and the number format of their Markdown tables.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <string>

#include <Eigen/Core>
#include <Eigen/LU>

namespace mapmerge::bench {

/// An estimate's errors against the truth.
struct Errors {
  double t_err, rot_deg, trans_m;
  /// Within the benches' success bounds: rotation < 5 deg and translation < 0.3 m.
  bool success() const { return rot_deg < 5.0 && trans_m < 0.3; }
};

/// T_R maps target (world) points into the source frame: T_source_target = T_R.
/// T_err = ||T_est * T_R^-1 - I||_F (the paper's); the translation error is that of T_target_source.
inline Errors errors(const Eigen::Matrix4d& T_est_target_source, const Eigen::Matrix4d& T_R) {
  const Eigen::Matrix4d T_est = T_est_target_source.inverse();  // estimate of T_R
  Errors e{};
  e.t_err = (T_est * T_R.inverse() - Eigen::Matrix4d::Identity()).norm();
  const Eigen::Matrix3d dR = T_est.topLeftCorner<3, 3>() * T_R.topLeftCorner<3, 3>().transpose();
  e.rot_deg = std::acos(std::clamp((dR.trace() - 1.0) / 2.0, -1.0, 1.0)) * 180.0 / M_PI;
  const Eigen::Matrix4d T_true_ts = T_R.inverse();
  e.trans_m = (T_est_target_source.topRightCorner<3, 1>() - T_true_ts.topRightCorner<3, 1>()).norm();
  return e;
}

/// `v` with `prec` decimals; "-" for NaN (no value), "inf" for an infinite fitness.
inline std::string fmt(double v, int prec = 3) {
  if (std::isnan(v)) return "-";
  if (std::isinf(v)) return "inf";
  char b[32];
  std::snprintf(b, sizeof b, "%.*f", prec, v);
  return b;
}

}  // namespace mapmerge::bench
