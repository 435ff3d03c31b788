#pragma once
// Internal: stage 2, the minimum-variance path tree from the reference over active edges
// (Dijkstra on WorkEdge::tree_cost). Gives the initial poses, the chaining baseline, and
// covariances propagated along the tree (first order, edges independent).

#include <vector>

#include "work_graph.hpp"

namespace mapmerge::graph::detail {

struct Tree {
  std::vector<char> reached;               // connected to the reference
  std::vector<int> parent_edge;            // -1: reference or not reached
  std::vector<Eigen::Isometry3d> T_global;  // T_global_robot; identity when not reached
  std::vector<Matrix6d> covariance;        // [position; rotation] global (RobotSolution convention)
};

Tree build_tree(const WorkGraph& graph);

/// SE(3) left-perturbation covariance [rho; phi] -> [position; rotation] of a pose at `position`.
Matrix6d decoupled_covariance(const Matrix6d& left, const Eigen::Vector3d& position);

}  // namespace mapmerge::graph::detail
