#include "solve_ceres.hpp"

#include <array>
#include <memory>

#include <ceres/ceres.h>

namespace mapmerge::graph::detail {
namespace {

/// Whitened error of one edge: sqrt_info * [rho; phi] of E = T_measured^-1 * (T_global_t^-1 T_global_s).
class EdgeCost {
 public:
  EdgeCost(const Eigen::Isometry3d& T_target_source, const Matrix6d& information)
      : q_measured_inv_(Eigen::Quaterniond(T_target_source.linear()).conjugate()),
        p_measured_(T_target_source.translation()),
        sqrt_information_(information.llt().matrixU()) {}

  template <typename T>
  bool operator()(const T* p_t, const T* q_t, const T* p_s, const T* q_s, T* residual) const {
    using Vec3 = Eigen::Matrix<T, 3, 1>;
    const Eigen::Map<const Vec3> pt(p_t), ps(p_s);
    const Eigen::Map<const Eigen::Quaternion<T>> qt(q_t), qs(q_s);
    const Eigen::Quaternion<T> qt_inv = qt.conjugate();
    const Eigen::Quaternion<T> q_est = qt_inv * qs;
    const Vec3 p_est = qt_inv * (ps - pt);
    const Eigen::Quaternion<T> q_meas_inv = q_measured_inv_.template cast<T>();
    Eigen::Quaternion<T> q_err = q_meas_inv * q_est;
    const Vec3 p_err = q_meas_inv * (p_est - p_measured_.template cast<T>());
    if (q_err.w() < T(0)) q_err.coeffs() = -q_err.coeffs();
    Eigen::Matrix<T, 6, 1> e;
    e << p_err, T(2) * q_err.vec();
    Eigen::Map<Eigen::Matrix<T, 6, 1>> r(residual);
    r = sqrt_information_.template cast<T>() * e;
    return true;
  }

  static ceres::CostFunction* create(const Edge& edge) {
    return new ceres::AutoDiffCostFunction<EdgeCost, 6, 3, 4, 3, 4>(
        new EdgeCost(edge.T_target_source, edge.information));
  }

  EIGEN_MAKE_ALIGNED_OPERATOR_NEW

 private:
  Eigen::Quaterniond q_measured_inv_;
  Eigen::Vector3d p_measured_;
  Matrix6d sqrt_information_;
};

ceres::LossFunction* make_loss(const SolverConfig& c) {
  switch (c.loss) {
    case RobustLoss::kHuber: return new ceres::HuberLoss(c.loss_scale);
    case RobustLoss::kCauchy: return new ceres::CauchyLoss(c.loss_scale);
    case RobustLoss::kNone: break;
  }
  return nullptr;
}

/// Parameter blocks: position [3] and Eigen quaternion [x y z w] per node.
struct Blocks {
  std::vector<std::array<double, 3>> p;
  std::vector<std::array<double, 4>> q;

  explicit Blocks(const std::vector<Eigen::Isometry3d>& poses) : p(poses.size()), q(poses.size()) {
    for (std::size_t i = 0; i < poses.size(); ++i) {
      Eigen::Map<Eigen::Vector3d>(p[i].data()) = poses[i].translation();
      Eigen::Map<Eigen::Quaterniond>(q[i].data()) = Eigen::Quaterniond(poses[i].linear()).normalized();
    }
  }
  Eigen::Isometry3d pose(std::size_t i) const {
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    T.linear() = Eigen::Map<const Eigen::Quaterniond>(q[i].data()).normalized().toRotationMatrix();
    T.translation() = Eigen::Map<const Eigen::Vector3d>(p[i].data());
    return T;
  }
};

/// Builds the problem; returns the number of residual blocks.
int build(const WorkGraph& g, const std::vector<char>& connected, const SolverConfig& c,
          Blocks& b, ceres::Problem& problem) {
  int residuals = 0;
  auto* manifold = new ceres::EigenQuaternionManifold;  // owned by the problem
  for (const WorkEdge& e : g.edges) {
    if (!e.active || !connected[e.source] || !connected[e.target]) continue;
    problem.AddResidualBlock(EdgeCost::create(*e.edge), make_loss(c), b.p[e.target].data(),
                             b.q[e.target].data(), b.p[e.source].data(), b.q[e.source].data());
    ++residuals;
  }
  for (std::size_t i = 0; i < g.nodes.size(); ++i) {
    if (!connected[i] || !problem.HasParameterBlock(b.q[i].data())) continue;
    problem.SetManifold(b.q[i].data(), manifold);
  }
  if (residuals == 0) {
    delete manifold;
    return 0;
  }
  if (problem.HasParameterBlock(b.p[g.reference].data())) {
    problem.SetParameterBlockConstant(b.p[g.reference].data());
    problem.SetParameterBlockConstant(b.q[g.reference].data());
  }
  return residuals;
}

ceres::Problem::Options problem_options() {
  ceres::Problem::Options o;
  o.manifold_ownership = ceres::TAKE_OWNERSHIP;
  o.loss_function_ownership = ceres::TAKE_OWNERSHIP;
  o.cost_function_ownership = ceres::TAKE_OWNERSHIP;
  return o;
}

}  // namespace

SolveResult solve_poses(const WorkGraph& g, const std::vector<char>& connected,
                        std::vector<Eigen::Isometry3d>& poses, const SolverConfig& c) {
  SolveResult out;
  Blocks b(poses);
  ceres::Problem problem(problem_options());
  if (build(g, connected, c, b, problem) == 0) {
    out.converged = true;
    out.message = "nothing to optimise";
    return out;
  }
  ceres::Solver::Options options;
  // Sparse normal Cholesky is about twice as fast as the dense one already at 16 robots
  // (bench/results/graph.md); dense only when Ceres was built without a sparse library.
  options.linear_solver_type = options.sparse_linear_algebra_library_type == ceres::NO_SPARSE
                                   ? ceres::DENSE_NORMAL_CHOLESKY
                                   : ceres::SPARSE_NORMAL_CHOLESKY;
  options.max_num_iterations = c.max_iterations;
  options.function_tolerance = c.function_tolerance;
  options.num_threads = 1;
  options.logging_type = ceres::SILENT;
  options.minimizer_progress_to_stdout = false;
  ceres::Solver::Summary summary;
  ceres::Solve(options, &problem, &summary);
  out.converged = summary.termination_type == ceres::CONVERGENCE;
  out.iterations = static_cast<int>(summary.iterations.size());
  out.initial_cost = summary.initial_cost;
  out.final_cost = summary.final_cost;
  out.message = summary.message;
  if (summary.IsSolutionUsable()) {
    for (std::size_t i = 0; i < poses.size(); ++i)
      if (connected[i]) poses[i] = b.pose(i);
  }
  return out;
}

bool estimate_covariance(const WorkGraph& g, const std::vector<char>& connected,
                         const std::vector<Eigen::Isometry3d>& poses, const SolverConfig& c,
                         std::vector<Matrix6d>& covariance) {
  Blocks b(poses);
  ceres::Problem problem(problem_options());
  if (build(g, connected, c, b, problem) == 0) return true;
  // Gauss-Newton marginals: Sigma = (J^T J)^-1 over the free blocks, J in the tangent spaces
  // with the robust loss applied: what ceres::Covariance computes, densely, in well under a
  // millisecond for a fleet (ceres::Covariance's sparse QR takes several).
  ceres::Problem::EvaluateOptions options;
  std::vector<std::size_t> free_nodes;
  for (std::size_t i = 0; i < g.nodes.size(); ++i) {
    if (!connected[i] || static_cast<int>(i) == g.reference) continue;
    if (!problem.HasParameterBlock(b.p[i].data())) continue;
    free_nodes.push_back(i);
    options.parameter_blocks.push_back(b.p[i].data());
    options.parameter_blocks.push_back(b.q[i].data());
  }
  if (free_nodes.empty()) return true;
  options.apply_loss_function = true;
  options.num_threads = 1;
  ceres::CRSMatrix jacobian;
  if (!problem.Evaluate(options, nullptr, nullptr, nullptr, &jacobian)) return false;
  const Eigen::Index n = 6 * static_cast<Eigen::Index>(free_nodes.size());
  if (jacobian.num_cols != n) return false;
  Eigen::MatrixXd H = Eigen::MatrixXd::Zero(n, n);
  for (int r = 0; r < jacobian.num_rows; ++r) {
    for (int a = jacobian.rows[r]; a < jacobian.rows[r + 1]; ++a)
      for (int k = jacobian.rows[r]; k < jacobian.rows[r + 1]; ++k)
        H(jacobian.cols[a], jacobian.cols[k]) += jacobian.values[a] * jacobian.values[k];
  }
  const Eigen::LLT<Eigen::MatrixXd> llt(H);
  if (llt.info() != Eigen::Success) return false;
  const Eigen::MatrixXd sigma = llt.solve(Eigen::MatrixXd::Identity(n, n));
  // The quaternion tangent is the half angle: theta = 2 delta.
  Matrix6d scale = Matrix6d::Identity();
  scale.bottomRightCorner<3, 3>() *= 2.0;
  for (std::size_t k = 0; k < free_nodes.size(); ++k) {
    const Eigen::Index o = 6 * static_cast<Eigen::Index>(k);
    const Matrix6d block = sigma.block<6, 6>(o, o);
    covariance[free_nodes[k]] = scale * block * scale;
    if (!covariance[free_nodes[k]].allFinite()) return false;
  }
  return true;
}

}  // namespace mapmerge::graph::detail
