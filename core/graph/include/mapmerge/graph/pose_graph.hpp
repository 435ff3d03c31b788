#pragma once
/// Fleet pose graph (issue 8): nodes are robot map frames, edges accepted pairwise alignments.
///
///   PoseGraph g;  g.set_reference("r0");
///   g.add_or_update_edge({"r1", "r0", T_r0_r1, info});   // source, target, T_target_source
///   GraphSolution s = g.optimise(config);                // cycle checks -> tree -> Ceres
///   s.robot("r1")->T_global_robot, ->connected, ->quality
///
/// optimise() is incremental: it warm-starts from the last solution and returns the cached
/// solution when nothing changed. "Cannot solve" is a value (GraphSolution::valid == false with
/// a reason); malformed edges throw std::invalid_argument. Not thread-safe: one owner (the
/// server's scheduler) or an external mutex.

#include <cstddef>
#include <map>
#include <string>
#include <vector>

#include <Eigen/Core>
#include <Eigen/Geometry>

#include "mapmerge/graph/config.hpp"
#include "mapmerge/graph/information.hpp"

namespace mapmerge::graph {

using RobotId = std::string;

/// One accepted pairwise alignment.
struct Edge {
  RobotId source;   ///< robot whose map frame is mapped into the target's
  RobotId target;
  Eigen::Isometry3d T_target_source = Eigen::Isometry3d::Identity();  ///< source points -> target frame
  Matrix6d information = Matrix6d::Identity();  ///< of [rho (m); phi (rad)], see information.hpp
  std::string id;   ///< empty: "<target>|<source>" (one edge per ordered pair)
};

enum class EdgeState {
  kAccepted,      ///< used by the solution
  kRejected,      ///< inconsistent with the rest of the graph; left out (see reason, evidence)
  kNotConnected,  ///< consistent but neither end is connected to the reference
};

/// One loop through an edge and how well it closes.
struct CycleEvidence {
  std::vector<std::string> edges;  ///< edge ids around the loop, starting with the edge itself
  double rotation_error_deg = 0.0;     ///< rotation angle of the loop transform [deg]
  double translation_error = 0.0;      ///< translation of the loop transform [m]
  double rotation_tolerance_deg = 0.0;  ///< [deg]
  double translation_tolerance = 0.0;   ///< [m]
  bool consistent = false;
};

struct EdgeSolution {
  std::string id;
  RobotId source;
  RobotId target;
  EdgeState state = EdgeState::kAccepted;
  bool verified = false;            ///< lies on at least one closed, consistent loop
  int consistent_cycles = 0;        ///< loops through the edge that close (final graph, or at rejection) [count]
  int inconsistent_cycles = 0;      ///< loops through the edge that do not close [count]
  double residual_rotation_deg = 0.0;  ///< |E| of the edge against the solved poses [deg]; 0 when not both ends connected
  double residual_translation = 0.0;   ///< [m]
  std::string reason;               ///< why rejected (empty otherwise)
  std::vector<CycleEvidence> evidence;  ///< rejected: worst loops (cycle rejection) at the time of rejection
};

struct RobotSolution {
  RobotId id;
  bool connected = false;  ///< T_global_robot is valid (reachable from the reference over accepted edges)
  bool verified = false;   ///< the reference, or one of its accepted edges is verified
  Eigen::Isometry3d T_global_robot = Eigen::Isometry3d::Identity();  ///< identity when not connected
  Matrix6d covariance = Matrix6d::Zero();  ///< of [position (m); rotation (rad)], global frame; rotation R = Exp(theta) * R_hat
  double sigma_translation = 0.0;  ///< sqrt of the largest eigenvalue of the position block [m]
  double sigma_rotation_deg = 0.0;  ///< same for the rotation block [deg]
  double quality = 0.0;    ///< [0..1], see QualityConfig; 0 when not connected, 1 for the reference
  int accepted_edges = 0;  ///< [count]
  int rejected_edges = 0;  ///< [count]
};

struct SolverSummary {
  bool optimised = false;       ///< Ceres ran (false for chain() or a graph without free robot)
  bool converged = false;       ///< Ceres reported convergence
  bool warm_started = false;    ///< at least one robot started from the last solution
  int iterations = 0;           ///< summed over the rejection rounds [count]
  int rejection_rounds = 0;     ///< re-solves after residual rejection [count]
  double initial_cost = 0.0;    ///< first round [0.5 * sum of robustified squared whitened residuals]
  double final_cost = 0.0;      ///< last round
  bool covariance_from_solver = false;  ///< marginals of the solved problem (else propagated along the tree)
  double consistency_ms = 0.0;  ///< cycle checks [ms]
  double solve_ms = 0.0;        ///< Ceres solves [ms]
  double covariance_ms = 0.0;   ///< [ms]
  double total_ms = 0.0;        ///< the whole call [ms]
  std::string message;          ///< Ceres' last report line
};

struct GraphSolution {
  bool valid = false;        ///< false: no reference set; see reason
  std::string reason;
  RobotId reference;
  std::vector<RobotSolution> robots;  ///< sorted by id
  std::vector<EdgeSolution> edges;    ///< sorted by id
  SolverSummary summary;

  const RobotSolution* robot(const RobotId& id) const;   ///< nullptr when unknown
  const EdgeSolution* edge(const std::string& id) const;  ///< nullptr when unknown
};

/// Default id of an edge: "<target>|<source>".
std::string default_edge_id(const RobotId& source, const RobotId& target);

class PoseGraph {
 public:
  /// The robot whose frame is the global frame (fixed in the optimisation).
  void set_reference(const RobotId& id);
  const RobotId& reference() const { return reference_; }

  /// Makes a robot known without edges (reported as not connected). Idempotent.
  void add_robot(const RobotId& id);
  /// Adds the edge or replaces the one with the same id; returns the id. Throws
  /// std::invalid_argument for empty/equal robot ids, a non-finite or non-rigid transform, or an
  /// information matrix that is not symmetric positive definite.
  std::string add_or_update_edge(const Edge& edge);
  /// Returns false when no edge has this id.
  bool remove_edge(const std::string& id);
  /// Removes the robot and all its edges (the reference stays the reference id).
  void remove_robot(const RobotId& id);

  const std::map<std::string, Edge>& edges() const { return edges_; }
  std::vector<RobotId> robots() const;  ///< sorted; every robot named by an edge, added, or the reference

  /// Cycle checks, tree initialisation, joint optimisation with a robust loss, residual
  /// rejection, covariances. Warm-starts from the last solution; returns it unchanged when the
  /// graph and config did not change since.
  GraphSolution optimise(const GraphConfig& config);
  /// Baseline: the same cycle checks, then poses composed along the minimum-variance spanning
  /// tree from the reference (sequential merging), no optimisation; covariances propagated.
  GraphSolution chain(const GraphConfig& config) const;

 private:
  RobotId reference_;
  std::map<RobotId, int> robots_;     // explicitly added robots (value unused)
  std::map<std::string, Edge> edges_;
  std::map<RobotId, Eigen::Isometry3d> last_poses_;  // warm start
  GraphSolution last_solution_;
  GraphConfig last_config_;
  bool dirty_ = true;
};

}  // namespace mapmerge::graph
