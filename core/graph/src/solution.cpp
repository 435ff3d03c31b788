#include "solution.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>

#include <Eigen/Eigenvalues>

namespace mapmerge::graph {
namespace detail {
namespace {

double quality_of(const RobotSolution& r, const QualityConfig& q) {
  const double a = r.sigma_translation / q.translation_scale;
  const double b = r.sigma_rotation_deg / q.rotation_scale_deg;
  return std::exp(-0.5 * (a * a + b * b)) * (r.verified ? 1.0 : q.unverified_factor);
}

double largest_sigma(const Eigen::Matrix3d& block) {
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es(0.5 * (block + block.transpose()),
                                                          Eigen::EigenvaluesOnly);
  return std::sqrt(std::max(0.0, es.eigenvalues().maxCoeff()));
}

}  // namespace

Residual edge_residual(const WorkEdge& e, const std::vector<Eigen::Isometry3d>& poses,
                       const ConsistencyConfig& c) {
  const Eigen::Isometry3d T_est = poses[e.target].inverse() * poses[e.source];
  const Eigen::Isometry3d E = e.edge->T_target_source.inverse() * T_est;
  Residual r;
  r.rotation_deg = rotation_angle_deg(E.linear());
  r.translation = E.translation().norm();
  // A rotation error of the alignment moves the source origin by its lever arm.
  const double t_tol = c.translation_threshold +
                       c.rotation_threshold_deg / kDegPerRad * e.edge->T_target_source.translation().norm();
  r.badness = std::max(r.rotation_deg / c.rotation_threshold_deg, r.translation / t_tol);
  return r;
}

/// Rejects the accepted edge with the largest residual beyond tolerance; false if none.
bool reject_worst_residual(WorkGraph& g, const std::vector<char>& connected,
                           const std::vector<Eigen::Isometry3d>& poses, const ConsistencyConfig& c) {
  int worst = -1;
  Residual worst_r;
  for (std::size_t k = 0; k < g.edges.size(); ++k) {
    const WorkEdge& e = g.edges[k];
    if (!e.active || !connected[e.source] || !connected[e.target]) continue;
    const Residual r = edge_residual(e, poses, c);
    if (r.badness > 1.0 && r.badness > worst_r.badness) {
      worst = static_cast<int>(k);
      worst_r = r;
    }
  }
  if (worst < 0) return false;
  WorkEdge& e = g.edges[worst];
  e.active = false;
  e.report.state = EdgeState::kRejected;
  e.report.verified = false;
  char buf[200];
  std::snprintf(buf, sizeof buf,
                "residual after optimisation: rotation %.2f deg, translation %.3f m (%.1fx the tolerance)",
                worst_r.rotation_deg, worst_r.translation, worst_r.badness);
  e.report.reason = buf;
  return true;
}

/// Initial poses: the tree's, or the last solution's where it agrees with the tree.
bool warm_start(const WorkGraph& g, const Tree& tree,
                const std::map<RobotId, Eigen::Isometry3d>& last, const SolverConfig& c,
                std::vector<Eigen::Isometry3d>& poses) {
  poses = tree.T_global;
  bool any = false;
  if (!c.warm_start) return false;
  for (std::size_t i = 0; i < g.nodes.size(); ++i) {
    if (!tree.reached[i] || static_cast<int>(i) == g.reference) continue;
    const auto it = last.find(g.nodes[i]);
    if (it == last.end()) continue;
    const Eigen::Isometry3d d = tree.T_global[i].inverse() * it->second;
    if (rotation_angle_deg(d.linear()) > c.warm_start_max_rotation_deg ||
        d.translation().norm() > c.warm_start_max_translation)
      continue;
    poses[i] = it->second;
    any = true;
  }
  return any;
}

/// Fills the per-edge and per-robot reports from the final state.
void fill_solution(const WorkGraph& g, const std::vector<char>& connected,
            const std::vector<Eigen::Isometry3d>& poses, const std::vector<Matrix6d>& covariance,
            const GraphConfig& config, GraphSolution& out) {
  out.edges.clear();
  out.robots.clear();
  std::vector<RobotSolution> robots(g.nodes.size());
  for (std::size_t i = 0; i < g.nodes.size(); ++i) robots[i].id = g.nodes[i];
  for (const WorkEdge& e : g.edges) {
    EdgeSolution r = e.report;
    if (e.active) {
      const bool both = connected[e.source] && connected[e.target];
      r.state = both ? EdgeState::kAccepted : EdgeState::kNotConnected;
      if (both) {
        const Residual res = edge_residual(e, poses, config.consistency);
        r.residual_rotation_deg = res.rotation_deg;
        r.residual_translation = res.translation;
      }
      for (int n : {e.source, e.target}) {
        ++robots[n].accepted_edges;
        robots[n].verified = robots[n].verified || r.verified;
      }
    } else {
      ++robots[e.source].rejected_edges;
      ++robots[e.target].rejected_edges;
    }
    out.edges.push_back(std::move(r));
  }
  for (std::size_t i = 0; i < g.nodes.size(); ++i) {
    RobotSolution& r = robots[i];
    r.connected = connected[i] != 0;
    if (!r.connected) {
      r.verified = false;
      continue;
    }
    r.T_global_robot = poses[i];
    if (static_cast<int>(i) == g.reference) {
      r.verified = true;
      r.quality = 1.0;
      continue;
    }
    r.covariance = covariance[i];
    r.sigma_translation = largest_sigma(r.covariance.topLeftCorner<3, 3>());
    r.sigma_rotation_deg = largest_sigma(r.covariance.bottomRightCorner<3, 3>()) * kDegPerRad;
    r.quality = quality_of(r, config.quality);
  }
  out.robots = std::move(robots);
}

GraphSolution invalid_solution(const std::vector<RobotId>& robots, const std::string& why) {
  GraphSolution s;
  s.valid = false;
  s.reason = why;
  for (const RobotId& id : robots) {
    RobotSolution r;
    r.id = id;
    s.robots.push_back(r);
  }
  return s;
}

}  // namespace detail

const RobotSolution* GraphSolution::robot(const RobotId& id) const {
  const auto it = std::lower_bound(robots.begin(), robots.end(), id,
                                   [](const RobotSolution& r, const RobotId& v) { return r.id < v; });
  return it != robots.end() && it->id == id ? &*it : nullptr;
}

const EdgeSolution* GraphSolution::edge(const std::string& id) const {
  for (const EdgeSolution& e : edges)
    if (e.id == id) return &e;
  return nullptr;
}

}  // namespace mapmerge::graph
