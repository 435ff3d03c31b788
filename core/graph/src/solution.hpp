#pragma once
// Internal: what happens after the cycle checks: residuals of edges against solved poses and
// their rejection, the warm start, and the per-robot / per-edge report (quality figure).

#include <map>
#include <string>
#include <vector>

#include "mapmerge/graph/pose_graph.hpp"
#include "spanning_tree.hpp"
#include "work_graph.hpp"

namespace mapmerge::graph::detail {

/// Residual of an edge against the poses and how far it is beyond its tolerance (> 1: beyond).
struct Residual {
  double rotation_deg = 0.0;
  double translation = 0.0;
  double badness = 0.0;
};

Residual edge_residual(const WorkEdge& e, const std::vector<Eigen::Isometry3d>& poses,
                       const ConsistencyConfig& c);

/// Rejects the accepted edge with the largest residual beyond tolerance; false if none.
bool reject_worst_residual(WorkGraph& g, const std::vector<char>& connected,
                           const std::vector<Eigen::Isometry3d>& poses, const ConsistencyConfig& c);

/// Initial poses: the tree's, or the last solution's where it agrees with the tree. True when
/// at least one robot starts from the last solution.
bool warm_start(const WorkGraph& g, const Tree& tree, const std::map<RobotId, Eigen::Isometry3d>& last,
                const SolverConfig& c, std::vector<Eigen::Isometry3d>& poses);

/// Fills the per-edge and per-robot reports of `out` from the final state.
void fill_solution(const WorkGraph& g, const std::vector<char>& connected,
                   const std::vector<Eigen::Isometry3d>& poses, const std::vector<Matrix6d>& covariance,
                   const GraphConfig& config, GraphSolution& out);

GraphSolution invalid_solution(const std::vector<RobotId>& robots, const std::string& why);

}  // namespace mapmerge::graph::detail
