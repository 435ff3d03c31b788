#include "mapmerge/graph/pose_graph.hpp"

#include <algorithm>
#include <chrono>
#include <stdexcept>
#include <tuple>

#include <Eigen/Cholesky>

#include "consistency.hpp"
#include "solve_ceres.hpp"
#include "solution.hpp"
#include "spanning_tree.hpp"
#include "work_graph.hpp"

namespace mapmerge::graph {

using detail::WorkGraph;

namespace {

using Clock = std::chrono::steady_clock;
double ms_since(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

/// What optimise() and chain() start from: the work graph of `graph`'s edges with its cycles
/// checked; `out` marked valid, with the reference and the consistency check's time.
WorkGraph checked_work_graph(const PoseGraph& graph, const GraphConfig& config, GraphSolution& out) {
  out.valid = true;
  out.reference = graph.reference();
  WorkGraph g = detail::build_work_graph(graph.reference(), graph.robots(), graph.edges(), config.tree);
  const auto t = Clock::now();
  detail::check_consistency(g, config.consistency);
  out.summary.consistency_ms = ms_since(t);
  return g;
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

}  // namespace

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
  if (reference_.empty()) return detail::invalid_solution(robots(), "no reference robot set");
  GraphSolution out;
  WorkGraph g = checked_work_graph(*this, config, out);

  detail::Tree tree;
  std::vector<Eigen::Isometry3d> poses;
  auto t = Clock::now();
  for (int round = 0;; ++round) {
    tree = detail::build_tree(g);
    out.summary.warm_started = detail::warm_start(g, tree, last_poses_, config.solver, poses) || out.summary.warm_started;
    const detail::SolveResult r = detail::solve_poses(g, tree.reached, poses, config.solver);
    out.summary.optimised = true;
    out.summary.converged = r.converged;
    out.summary.iterations += r.iterations;
    if (round == 0) out.summary.initial_cost = r.initial_cost;
    out.summary.final_cost = r.final_cost;
    out.summary.message = r.message;
    out.summary.rejection_rounds = round;
    if (round >= config.solver.max_rejection_rounds ||
        !detail::reject_worst_residual(g, tree.reached, poses, config.consistency))
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

  detail::fill_solution(g, tree.reached, poses, covariance, config, out);
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
  if (reference_.empty()) return detail::invalid_solution(robots(), "no reference robot set");
  GraphSolution out;
  const WorkGraph g = checked_work_graph(*this, config, out);
  const detail::Tree tree = detail::build_tree(g);
  detail::fill_solution(g, tree.reached, tree.T_global, tree.covariance, config, out);
  out.summary.total_ms = ms_since(t0);
  return out;
}

}  // namespace mapmerge::graph
