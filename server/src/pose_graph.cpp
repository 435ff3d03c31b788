#include "mapmerge/server/pose_graph.hpp"

#include <functional>
#include <queue>
#include <utility>

namespace mapmerge::server {

Eigen::Matrix4d rigid_inverse(const Eigen::Matrix4d& T) {
  Eigen::Matrix4d inv = Eigen::Matrix4d::Identity();
  inv.topLeftCorner<3, 3>() = T.topLeftCorner<3, 3>().transpose();
  inv.topRightCorner<3, 1>() = -inv.topLeftCorner<3, 3>() * T.topRightCorner<3, 1>();
  return inv;
}

namespace {

/// A directed step: from `from`'s frame to `to`'s frame, T_from_to.
struct Step {
  std::string to;
  Eigen::Matrix4d T_from_to;
  double fitness;
};

std::map<std::string, std::vector<Step>> adjacency(const std::vector<Edge>& edges) {
  std::map<std::string, std::vector<Step>> adj;
  for (const Edge& e : edges) {
    adj[e.target].push_back({e.source, e.T_target_source, e.fitness});
    adj[e.source].push_back({e.target, rigid_inverse(e.T_target_source), e.fitness});
  }
  return adj;
}

}  // namespace

std::map<std::string, GlobalPose> global_poses(const std::string& reference,
                                               const std::vector<Edge>& edges, double hop_cost) {
  std::map<std::string, GlobalPose> poses;
  if (reference.empty()) return poses;
  const auto adj = adjacency(edges);
  std::map<std::string, double> cost{{reference, 0.0}};
  using Item = std::pair<double, std::string>;
  std::priority_queue<Item, std::vector<Item>, std::greater<Item>> open;
  open.push({0.0, reference});
  poses[reference] = GlobalPose{};
  while (!open.empty()) {
    const auto [c, node] = open.top();
    open.pop();
    if (c > cost[node]) continue;
    const auto it = adj.find(node);
    if (it == adj.end()) continue;
    for (const Step& s : it->second) {
      const double next = c + s.fitness + hop_cost;
      const auto known = cost.find(s.to);
      if (known != cost.end() && known->second <= next) continue;
      cost[s.to] = next;
      const GlobalPose& from = poses[node];
      poses[s.to] = GlobalPose{from.T_global_robot * s.T_from_to, std::max(from.fitness, s.fitness),
                               from.hops + 1};
      open.push({next, s.to});
    }
  }
  return poses;
}

}  // namespace mapmerge::server
