#include "mapmerge/graph/pose_graph.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <stdexcept>
#include <tuple>

#include <Eigen/Eigenvalues>

#include "consistency.hpp"
#include "solve_ceres.hpp"
#include "spanning_tree.hpp"
#include "work_graph.hpp"

namespace mapmerge::graph {

using detail::WorkEdge;
using detail::WorkGraph;

namespace {

using Clock = std::chrono::steady_clock;
double ms_since(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

void check_edge(const Edge& e) {
  if (e.source.empty() || e.target.empty()) throw std::invalid_argument("edge: empty robot id");
  if (e.source == e.target) throw std::invalid_argument("edge: source == target (" + e.source + ")");
  const Eigen::Matrix4d& m = e.T_target_source.matrix();
  if (!m.allFinite()) throw std::invalid_argument("edge " + e.target + "|" + e.source + ": transform not finite");
  const Eigen::Matrix3d R = e.T_target_source.linear();
  if (!(R.transpose() * R).isApprox(Eigen::Matrix3d::Identity(), 1e-6) || R.determinant() < 0.0)
    throw std::invalid_argument("edge " + e.target + "|" + e.source + ": rotation not orthonormal");
  if (!e.information.allFinite() || !e.information.isApprox(e.information.transpose(), 1e-9))
    throw std::invalid_argument("edge " + e.target + "|" + e.source + ": information not finite and symmetric");
  Eigen::LLT<Matrix6d> llt(e.information);
  if (llt.info() != Eigen::Success)
    throw std::invalid_argument("edge " + e.target + "|" + e.source + ": information not positive definite");
}

bool same(const GraphConfig& a, const GraphConfig& b) {
  const auto& ca = a.consistency;
  const auto& cb = b.consistency;
  const auto& sa = a.solver;
  const auto& sb = b.solver;
  const auto& qa = a.quality;
  const auto& qb = b.quality;
  return std::tie(ca.enabled, ca.rotation_threshold_deg, ca.translation_threshold, ca.max_cycle_length,
                  ca.max_cycles_per_edge, ca.max_evidence) ==
             std::tie(cb.enabled, cb.rotation_threshold_deg, cb.translation_threshold, cb.max_cycle_length,
                      cb.max_cycles_per_edge, cb.max_evidence) &&
         a.tree.lever_arm == b.tree.lever_arm &&
         std::tie(sa.loss, sa.loss_scale, sa.max_iterations, sa.function_tolerance, sa.max_rejection_rounds,
                  sa.warm_start, sa.warm_start_max_rotation_deg, sa.warm_start_max_translation,
                  sa.compute_covariance) ==
             std::tie(sb.loss, sb.loss_scale, sb.max_iterations, sb.function_tolerance, sb.max_rejection_rounds,
                      sb.warm_start, sb.warm_start_max_rotation_deg, sb.warm_start_max_translation,
                      sb.compute_covariance) &&
         std::tie(qa.translation_scale, qa.rotation_scale_deg, qa.unverified_factor) ==
             std::tie(qb.translation_scale, qb.rotation_scale_deg, qb.unverified_factor);
}

/// Residual of an edge against the poses and how far it is beyond its tolerance (> 1: beyond).
struct Residual {
  double rotation_deg = 0.0;
  double translation = 0.0;
  double badness = 0.0;
};

Residual residual(const WorkEdge& e, const std::vector<Eigen::Isometry3d>& poses,
                  const ConsistencyConfig& c) {
  const Eigen::Isometry3d T_est = poses[e.target].inverse() * poses[e.source];
  const Eigen::Isometry3d E = e.edge->T_target_source.inverse() * T_est;
  Residual r;
  r.rotation_deg = detail::rotation_angle_deg(E.linear());
  r.translation = E.translation().norm();
  // A rotation error of the alignment moves the source origin by its lever arm.
  const double t_tol = c.translation_threshold +
                       c.rotation_threshold_deg / detail::kDegPerRad * e.edge->T_target_source.translation().norm();
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
    const Residual r = residual(e, poses, c);
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
bool warm_start(const WorkGraph& g, const detail::Tree& tree,
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
    if (detail::rotation_angle_deg(d.linear()) > c.warm_start_max_rotation_deg ||
        d.translation().norm() > c.warm_start_max_translation)
      continue;
    poses[i] = it->second;
    any = true;
  }
  return any;
}

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

/// Fills the per-edge and per-robot reports from the final state.
void report(const WorkGraph& g, const std::vector<char>& connected,
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
        const Residual res = residual(e, poses, config.consistency);
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
    r.sigma_rotation_deg = largest_sigma(r.covariance.bottomRightCorner<3, 3>()) * detail::kDegPerRad;
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

}  // namespace

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

std::string default_edge_id(const RobotId& source, const RobotId& target) { return target + "|" + source; }

void PoseGraph::set_reference(const RobotId& id) {
  if (id.empty()) throw std::invalid_argument("reference: empty robot id");
  if (id != reference_) {
    reference_ = id;
    last_poses_.clear();  // a new global frame: old poses mean nothing
    dirty_ = true;
  }
}

void PoseGraph::add_robot(const RobotId& id) {
  if (id.empty()) throw std::invalid_argument("add_robot: empty robot id");
  if (robots_.emplace(id, 0).second) dirty_ = true;
}

std::string PoseGraph::add_or_update_edge(const Edge& edge) {
  check_edge(edge);
  Edge e = edge;
  if (e.id.empty()) e.id = default_edge_id(e.source, e.target);
  const std::string id = e.id;
  edges_[id] = std::move(e);
  dirty_ = true;
  return id;
}

bool PoseGraph::remove_edge(const std::string& id) {
  if (edges_.erase(id) == 0) return false;
  dirty_ = true;
  return true;
}

void PoseGraph::remove_robot(const RobotId& id) {
  robots_.erase(id);
  last_poses_.erase(id);
  for (auto it = edges_.begin(); it != edges_.end();)
    it = (it->second.source == id || it->second.target == id) ? edges_.erase(it) : std::next(it);
  dirty_ = true;
}

std::vector<RobotId> PoseGraph::robots() const {
  std::vector<RobotId> out;
  for (const auto& [id, unused] : robots_) out.push_back(id);
  for (const auto& [id, e] : edges_) {
    out.push_back(e.source);
    out.push_back(e.target);
  }
  if (!reference_.empty()) out.push_back(reference_);
  std::sort(out.begin(), out.end());
  out.erase(std::unique(out.begin(), out.end()), out.end());
  return out;
}

GraphSolution PoseGraph::optimise(const GraphConfig& config) {
  if (!dirty_ && same(config, last_config_) && last_solution_.valid) return last_solution_;
  const auto t0 = Clock::now();
  if (reference_.empty()) return invalid_solution(robots(), "no reference robot set");

  GraphSolution out;
  out.valid = true;
  out.reference = reference_;
  WorkGraph g = detail::build_work_graph(reference_, robots(), edges_, config.tree);
  auto t = Clock::now();
  detail::check_consistency(g, config.consistency);
  out.summary.consistency_ms = ms_since(t);

  detail::Tree tree;
  std::vector<Eigen::Isometry3d> poses;
  t = Clock::now();
  for (int round = 0;; ++round) {
    tree = detail::build_tree(g);
    out.summary.warm_started = warm_start(g, tree, last_poses_, config.solver, poses) || out.summary.warm_started;
    const detail::SolveResult r = detail::solve_poses(g, tree.reached, poses, config.solver);
    out.summary.optimised = true;
    out.summary.converged = r.converged;
    out.summary.iterations += r.iterations;
    if (round == 0) out.summary.initial_cost = r.initial_cost;
    out.summary.final_cost = r.final_cost;
    out.summary.message = r.message;
    out.summary.rejection_rounds = round;
    if (round >= config.solver.max_rejection_rounds ||
        !reject_worst_residual(g, tree.reached, poses, config.consistency))
      break;
  }
  out.summary.solve_ms = ms_since(t);

  t = Clock::now();
  std::vector<Matrix6d> covariance = tree.covariance;
  if (config.solver.compute_covariance)
    out.summary.covariance_from_solver =
        detail::estimate_covariance(g, tree.reached, poses, config.solver, covariance);
  if (!out.summary.covariance_from_solver) covariance = tree.covariance;
  out.summary.covariance_ms = ms_since(t);

  report(g, tree.reached, poses, covariance, config, out);
  last_poses_.clear();
  for (const RobotSolution& r : out.robots)
    if (r.connected) last_poses_[r.id] = r.T_global_robot;
  out.summary.total_ms = ms_since(t0);
  last_solution_ = out;
  last_config_ = config;
  dirty_ = false;
  return out;
}

GraphSolution PoseGraph::chain(const GraphConfig& config) const {
  const auto t0 = Clock::now();
  if (reference_.empty()) return invalid_solution(robots(), "no reference robot set");
  GraphSolution out;
  out.valid = true;
  out.reference = reference_;
  WorkGraph g = detail::build_work_graph(reference_, robots(), edges_, config.tree);
  auto t = Clock::now();
  detail::check_consistency(g, config.consistency);
  out.summary.consistency_ms = ms_since(t);
  const detail::Tree tree = detail::build_tree(g);
  report(g, tree.reached, tree.T_global, tree.covariance, config, out);
  out.summary.total_ms = ms_since(t0);
  return out;
}

}  // namespace mapmerge::graph
