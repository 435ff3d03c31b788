#pragma once
// Internal: stage 3, the joint optimisation (the only translation unit that sees Ceres).

#include <string>
#include <vector>

#include "mapmerge/graph/config.hpp"
#include "work_graph.hpp"

namespace mapmerge::graph::detail {

struct SolveResult {
  bool converged = false;
  int iterations = 0;
  double initial_cost = 0.0;
  double final_cost = 0.0;
  std::string message;
};

/// Optimises poses[i] of every connected node except the reference (fixed) over the active
/// edges whose both ends are connected. poses: T_global_robot, in (initial) and out.
SolveResult solve_poses(const WorkGraph& graph, const std::vector<char>& connected,
                        std::vector<Eigen::Isometry3d>& poses, const SolverConfig& config);

/// Marginal covariances [position; rotation] (global frame) of the connected non-reference
/// nodes at `poses`; false when ceres::Covariance fails (rank deficiency).
bool estimate_covariance(const WorkGraph& graph, const std::vector<char>& connected,
                         const std::vector<Eigen::Isometry3d>& poses, const SolverConfig& config,
                         std::vector<Matrix6d>& covariance);

}  // namespace mapmerge::graph::detail
