#pragma once
// Internal: the graph as the stages see it (dense node indices, edges with their running state)
// and the few SE(3) helpers they share.

#include <string>
#include <vector>

#include <Eigen/Core>
#include <Eigen/Geometry>

#include "mapmerge/graph/config.hpp"
#include "mapmerge/graph/pose_graph.hpp"

namespace mapmerge::graph::detail {

struct WorkEdge {
  const Edge* edge = nullptr;
  int source = -1;          // node index
  int target = -1;          // node index
  double tree_cost = 0.0;   // tr(Sigma_t) + lever^2 tr(Sigma_r) [m^2]
  Matrix6d covariance = Matrix6d::Zero();  // inverse of the information, [rho; phi] at the source origin
  bool active = true;       // not rejected
  EdgeSolution report;
};

struct WorkGraph {
  std::vector<RobotId> nodes;  // sorted
  int reference = -1;          // index in nodes, -1 when not set
  std::vector<WorkEdge> edges;
  std::vector<std::vector<int>> incident;  // node -> edge indices
};

WorkGraph build_work_graph(const RobotId& reference, const std::vector<RobotId>& robots,
                           const std::map<std::string, Edge>& edges, const TreeConfig& tree);

/// T_from_to along an edge walked from node `from` to the other end.
Eigen::Isometry3d walk(const WorkEdge& e, int from);
/// The other end of an edge.
inline int other_end(const WorkEdge& e, int node) { return e.source == node ? e.target : e.source; }

double rotation_angle_deg(const Eigen::Matrix3d& R);
Eigen::Matrix3d skew(const Eigen::Vector3d& v);
/// Adjoint of T for the [rho; phi] ordering: [[R, [t]x R], [0, R]].
Matrix6d adjoint(const Eigen::Isometry3d& T);
/// [rho; phi] of the error E = T_measured^-1 * T_estimated (first order, source frame).
Eigen::Matrix<double, 6, 1> edge_error(const Eigen::Isometry3d& T_measured,
                                       const Eigen::Isometry3d& T_estimated);

constexpr double kDegPerRad = 57.29577951308232;

}  // namespace mapmerge::graph::detail
