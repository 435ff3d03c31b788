#include "work_graph.hpp"

#include <algorithm>
#include <cmath>

namespace mapmerge::graph {

const char* to_string(RobustLoss loss) {
  switch (loss) {
    case RobustLoss::kNone: return "none";
    case RobustLoss::kHuber: return "huber";
    case RobustLoss::kCauchy: return "cauchy";
  }
  return "?";
}

namespace detail {

Eigen::Matrix3d skew(const Eigen::Vector3d& v) {
  Eigen::Matrix3d m;
  m << 0.0, -v.z(), v.y(), v.z(), 0.0, -v.x(), -v.y(), v.x(), 0.0;
  return m;
}

Matrix6d adjoint(const Eigen::Isometry3d& T) {
  Matrix6d ad = Matrix6d::Zero();
  const Eigen::Matrix3d R = T.linear();
  ad.topLeftCorner<3, 3>() = R;
  ad.topRightCorner<3, 3>() = skew(T.translation()) * R;
  ad.bottomRightCorner<3, 3>() = R;
  return ad;
}

double rotation_angle_deg(const Eigen::Matrix3d& R) {
  // acos((tr R - 1) / 2) loses precision near 0; the quaternion form does not.
  const Eigen::Quaterniond q(R);
  return 2.0 * std::atan2(q.vec().norm(), std::abs(q.w())) * kDegPerRad;
}

Eigen::Matrix<double, 6, 1> edge_error(const Eigen::Isometry3d& T_measured,
                                       const Eigen::Isometry3d& T_estimated) {
  const Eigen::Isometry3d E = T_measured.inverse() * T_estimated;
  Eigen::Quaterniond q(E.linear());
  if (q.w() < 0.0) q.coeffs() = -q.coeffs();
  Eigen::Matrix<double, 6, 1> e;
  e << E.translation(), 2.0 * q.vec();
  return e;
}

Eigen::Isometry3d walk(const WorkEdge& e, int from) {
  // T_target_source maps source points into the target: walking target -> source gives it.
  return from == e.target ? e.edge->T_target_source : e.edge->T_target_source.inverse();
}

WorkGraph build_work_graph(const RobotId& reference, const std::vector<RobotId>& robots,
                           const std::map<std::string, Edge>& edges, const TreeConfig& tree) {
  WorkGraph g;
  g.nodes = robots;  // sorted, unique
  auto index = [&](const RobotId& id) {
    return static_cast<int>(std::lower_bound(g.nodes.begin(), g.nodes.end(), id) - g.nodes.begin());
  };
  if (!reference.empty()) g.reference = index(reference);
  g.incident.resize(g.nodes.size());
  g.edges.reserve(edges.size());
  for (const auto& [id, edge] : edges) {
    WorkEdge w;
    w.edge = &edge;
    w.source = index(edge.source);
    w.target = index(edge.target);
    w.covariance = edge.information.inverse();
    w.covariance = 0.5 * (w.covariance + w.covariance.transpose());
    w.tree_cost = w.covariance.topLeftCorner<3, 3>().trace() +
                  tree.lever_arm * tree.lever_arm * w.covariance.bottomRightCorner<3, 3>().trace();
    w.report.id = id;
    w.report.source = edge.source;
    w.report.target = edge.target;
    const int k = static_cast<int>(g.edges.size());
    g.incident[w.source].push_back(k);
    g.incident[w.target].push_back(k);
    g.edges.push_back(std::move(w));
  }
  return g;
}

}  // namespace detail
}  // namespace mapmerge::graph
