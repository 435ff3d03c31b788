#include "spanning_tree.hpp"

#include <functional>
#include <limits>
#include <queue>
#include <utility>

namespace mapmerge::graph::detail {

Matrix6d decoupled_covariance(const Matrix6d& left, const Eigen::Vector3d& position) {
  // Exp([rho; phi]) * T moves the position by rho + phi x p = rho - [p]x phi.
  Matrix6d B = Matrix6d::Identity();
  B.topRightCorner<3, 3>() = -skew(position);
  return B * left * B.transpose();
}

namespace {

/// Right-perturbation covariance of T_parent_child along edge e walked from `parent`.
Matrix6d walked_covariance(const WorkEdge& e, int parent) {
  if (parent == e.target) return e.covariance;  // T_target_source itself, noise in the source frame
  // (T Exp(xi))^-1 = T^-1 Exp(-Ad_T xi)
  const Matrix6d ad = adjoint(e.edge->T_target_source);
  return ad * e.covariance * ad.transpose();
}

}  // namespace

Tree build_tree(const WorkGraph& g) {
  const std::size_t n = g.nodes.size();
  Tree t;
  t.reached.assign(n, 0);
  t.parent_edge.assign(n, -1);
  t.T_global.assign(n, Eigen::Isometry3d::Identity());
  t.covariance.assign(n, Matrix6d::Zero());
  if (g.reference < 0) return t;

  std::vector<double> dist(n, std::numeric_limits<double>::infinity());
  std::vector<Matrix6d> left(n, Matrix6d::Zero());
  using Item = std::pair<double, int>;
  std::priority_queue<Item, std::vector<Item>, std::greater<Item>> queue;
  dist[g.reference] = 0.0;
  queue.push({0.0, g.reference});
  while (!queue.empty()) {
    const auto [d, node] = queue.top();
    queue.pop();
    if (t.reached[node]) continue;
    t.reached[node] = 1;
    if (t.parent_edge[node] >= 0) {
      const WorkEdge& e = g.edges[t.parent_edge[node]];
      const int parent = other_end(e, node);
      t.T_global[node] = t.T_global[parent] * walk(e, parent);
      const Matrix6d ad = adjoint(t.T_global[node]);
      left[node] = left[parent] + ad * walked_covariance(e, parent) * ad.transpose();
      t.covariance[node] = decoupled_covariance(left[node], t.T_global[node].translation());
    }
    for (int k : g.incident[node]) {
      const WorkEdge& e = g.edges[k];
      if (!e.active) continue;
      const int next = other_end(e, node);
      const double nd = d + e.tree_cost;
      if (!t.reached[next] && nd < dist[next]) {
        dist[next] = nd;
        t.parent_edge[next] = k;
        queue.push({nd, next});
      }
    }
  }
  return t;
}

}  // namespace mapmerge::graph::detail
