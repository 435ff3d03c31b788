#pragma once
/// Settings of the fleet pose graph (issue 8). Plain structs, one per stage:
///   consistency (cycle checks) -> tree (initialisation, chaining) -> solver (Ceres, robust loss,
///   residual rejection) -> quality (uncertainty figure per robot).

namespace mapmerge::graph {

/// Stage 1: cycle consistency. A loop of k edges closes within
///   rotation:    rotation_threshold_deg * sqrt(k)
///   translation: sqrt(sum over edges (translation_threshold^2 + (rotation_threshold * d_i)^2))
/// where d_i is the distance of the edge's frames from the loop's start frame (a rotation error
/// moves far frames by its lever arm). Loops that do not close are inconsistent.
struct ConsistencyConfig {
  bool enabled = true;                 ///< false: no cycle checks (every edge is used)
  double rotation_threshold_deg = 2.0;  ///< per-edge rotation tolerance of a loop [deg]
  double translation_threshold = 0.15;  ///< per-edge translation tolerance of a loop [m]
  int max_cycle_length = 6;            ///< loops enumerated up to this many edges, shortest first [edges]
  int max_cycles_per_edge = 24;        ///< loops examined per edge [count]
  int max_evidence = 4;                ///< worst loops reported per rejected edge [count]
};

/// Stage 2: spanning tree from the reference (initial poses; the chaining baseline). The tree
/// is the minimum-variance path tree: an edge costs tr(Sigma_t) + lever_arm^2 * tr(Sigma_r).
struct TreeConfig {
  double lever_arm = 10.0;  ///< converts rotation variance into position variance in the edge cost [m]
};

enum class RobustLoss { kNone, kHuber, kCauchy };

/// Stage 3: joint optimisation of every T_global_robot (Ceres), then residual rejection.
struct SolverConfig {
  RobustLoss loss = RobustLoss::kCauchy;  ///< robust loss on each edge's whitened residual
  double loss_scale = 6.0;        ///< where the loss turns robust [whitened residual norm, i.e. sigmas];
                                  ///< generous: the information model is a proxy and real alignment
                                  ///< errors run above its sigmas (outliers are the cycle checks' job)
  int max_iterations = 50;        ///< Levenberg-Marquardt iterations [count]
  double function_tolerance = 1e-10;  ///< relative cost change that ends the solve [ratio]
  int max_rejection_rounds = 3;   ///< re-solves after rejecting an edge whose residual exceeds
                                  ///< the consistency thresholds [count]
  bool warm_start = true;         ///< start from the last solution where it agrees with the tree
  double warm_start_max_rotation_deg = 5.0;  ///< a last pose further than this from the tree's is not reused [deg]
  double warm_start_max_translation = 0.5;   ///< ... or further than this [m]
  bool compute_covariance = true;  ///< marginal covariances (J^T J)^-1 at the solution (else propagated along the tree)
};

/// Stage 4: quality figure of a pose, in [0, 1]:
///   quality = exp(-0.5 * ((sigma_t / translation_scale)^2 + (sigma_r / rotation_scale)^2))
///             * (verified ? 1 : unverified_factor)
/// with sigma_t, sigma_r the largest standard deviations of the pose's covariance.
struct QualityConfig {
  double translation_scale = 0.10;    ///< sigma_t that costs a factor exp(-0.5) [m]
  double rotation_scale_deg = 1.0;    ///< sigma_r that costs a factor exp(-0.5) [deg]
  double unverified_factor = 0.5;     ///< factor for a robot none of whose edges lies on a closed, consistent loop [0..1]
};

struct GraphConfig {
  ConsistencyConfig consistency;
  TreeConfig tree;
  SolverConfig solver;
  QualityConfig quality;
};

const char* to_string(RobustLoss loss);

}  // namespace mapmerge::graph
