#pragma once
/// Global poses from accepted pairwise alignments: every robot connected to the reference gets
/// T_global_robot by composing the transforms along the best path (edges weighted by fitness).

#include <cstddef>
#include <cstdint>
#include <map>
#include <string>
#include <vector>

#include <Eigen/Core>

namespace mapmerge::server {

/// An accepted pairwise alignment: T_target_source maps source-map points into the target map.
struct Edge {
  std::string target;
  std::string source;
  Eigen::Matrix4d T_target_source = Eigen::Matrix4d::Identity();
  double fitness = 0.0;  ///< mean inlier distance [m]; lower is better
  std::size_t inliers = 0;  ///< inlier pairs of the alignment [count]; 0: unknown (restored edge)
  double overlap = 0.0;     ///< estimated share of points seen by both maps [0..1]
  Eigen::Vector3d pivot_source = Eigen::Vector3d::Zero();  ///< centre of the overlap, source frame [m]
  /// Inverse covariance of the edge's error [rho (m); phi (rad)] (mapmerge::graph convention);
  /// all zero: not known (an edge from an old store), derived from the numbers above.
  Eigen::Matrix<double, 6, 6> information = Eigen::Matrix<double, 6, 6>::Zero();
};

/// What the fleet pose graph made of an edge (stored with it, reported on the status topic).
struct EdgeVerdict {
  std::string target;
  std::string source;
  std::string state;     ///< "accepted", "rejected" or "not_connected"
  std::string reason;    ///< why rejected (empty otherwise)
  std::string evidence;  ///< rejected: the worst loops through it, how far they stay open
};

/// One try at aligning a pair: not repeated while both maps are the same. robot_a < robot_b;
/// the hashes identify each map at the try (its payload bytes and its session).
struct PairAttempt {
  std::string robot_a;
  std::string robot_b;
  std::string kind;        ///< "search" (global, placing an unknown robot), "rescue" (the search
                           ///< again on denser features, idle work) or "extra" (refine from the
                           ///< pose estimates, global search as fallback)
  std::uint64_t hash_a = 0;
  std::uint64_t hash_b = 0;
  bool accepted = false;
  std::string reason;      ///< why not accepted
  double stamp_unix = 0.0;  ///< [s since epoch]
};

struct GlobalPose {
  Eigen::Matrix4d T_global_robot = Eigen::Matrix4d::Identity();
  double fitness = 0.0;  ///< worst fitness along the path [m]; 0 for the reference
  int hops = 0;          ///< edges between the robot and the reference
  double quality = -1.0; ///< [0..1] from the optimised fleet graph; < 0: composed path (no graph solution)
};

/// Poses of every robot reachable from `reference` (which gets the identity). Path cost is the
/// sum over edges of (fitness + hop_cost); robots not reachable are absent from the result.
std::map<std::string, GlobalPose> global_poses(const std::string& reference,
                                               const std::vector<Edge>& edges,
                                               double hop_cost = 0.01);

/// Inverse of a rigid transform.
Eigen::Matrix4d rigid_inverse(const Eigen::Matrix4d& T);

}  // namespace mapmerge::server
