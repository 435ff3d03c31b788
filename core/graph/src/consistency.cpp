#include "consistency.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <deque>
#include <tuple>

namespace mapmerge::graph::detail {
namespace {

struct Step {
  int edge;  // edge index
  int from;  // node it is walked from
};
using Path = std::vector<Step>;

/// Simple paths between the ends of one edge, not using that edge: iterative deepening, so the
/// shortest loops come first; at most `cap` of them.
class LoopFinder {
 public:
  LoopFinder(const WorkGraph& g, const ConsistencyConfig& c) : g_(g), c_(c), on_path_(g.nodes.size(), 0) {}

  std::vector<Path> loops_through(int edge) {
    out_.clear();
    const WorkEdge& e = g_.edges[edge];
    skip_ = edge;
    goal_ = e.target;
    const int max_path = std::max(1, c_.max_cycle_length - 1);
    on_path_[e.source] = 1;
    for (int len = 1; len <= max_path && out_.size() < cap(); ++len) dfs(e.source, len);
    on_path_[e.source] = 0;
    if (out_.empty()) add_shortest(e.source);
    return out_;
  }

 private:
  std::size_t cap() const { return static_cast<std::size_t>(std::max(1, c_.max_cycles_per_edge)); }

  void dfs(int node, int depth_left) {
    for (int k : g_.incident[node]) {
      if (out_.size() >= cap()) return;
      if (k == skip_ || !g_.edges[k].active) continue;
      const int next = other_end(g_.edges[k], node);
      if (next == goal_) {
        if (depth_left == 1) {
          path_.push_back({k, node});
          out_.push_back(path_);
          path_.pop_back();
        }
        continue;
      }
      if (depth_left == 1 || on_path_[next]) continue;
      on_path_[next] = 1;
      path_.push_back({k, node});
      dfs(next, depth_left - 1);
      path_.pop_back();
      on_path_[next] = 0;
    }
  }

  // Breadth-first shortest path of any length (loops longer than max_cycle_length).
  void add_shortest(int start) {
    std::vector<int> via(g_.nodes.size(), -1);
    std::vector<char> seen(g_.nodes.size(), 0);
    std::deque<int> queue{start};
    seen[start] = 1;
    while (!queue.empty() && !seen[goal_]) {
      const int node = queue.front();
      queue.pop_front();
      for (int k : g_.incident[node]) {
        if (k == skip_ || !g_.edges[k].active) continue;
        const int next = other_end(g_.edges[k], node);
        if (seen[next]) continue;
        seen[next] = 1;
        via[next] = k;
        queue.push_back(next);
      }
    }
    if (!seen[goal_]) return;  // a bridge: no loop at all
    Path p;
    for (int node = goal_; node != start;) {
      const int k = via[node];
      const int prev = other_end(g_.edges[k], node);
      p.push_back({k, prev});
      node = prev;
    }
    std::reverse(p.begin(), p.end());
    out_.push_back(std::move(p));
  }

  const WorkGraph& g_;
  const ConsistencyConfig& c_;
  std::vector<char> on_path_;
  Path path_;
  std::vector<Path> out_;
  int skip_ = -1;
  int goal_ = -1;
};

/// The loop edge(target -> source) + path(source -> target), evaluated in the target frame.
CycleEvidence close_loop(const WorkGraph& g, int edge, const Path& path, const ConsistencyConfig& c) {
  const double r_th = c.rotation_threshold_deg / kDegPerRad;
  const WorkEdge& e = g.edges[edge];
  CycleEvidence ev;
  ev.edges.push_back(e.report.id);
  Eigen::Isometry3d Q = walk(e, e.target);
  double prev_distance = 0.0;
  double t_var = 0.0;
  auto add_edge_tolerance = [&](double distance) {
    const double lever = std::max(prev_distance, distance);
    t_var += c.translation_threshold * c.translation_threshold + (r_th * lever) * (r_th * lever);
    prev_distance = distance;
  };
  add_edge_tolerance(Q.translation().norm());
  for (const Step& s : path) {
    Q = Q * walk(g.edges[s.edge], s.from);
    add_edge_tolerance(Q.translation().norm());
    ev.edges.push_back(g.edges[s.edge].report.id);
  }
  const double k = static_cast<double>(ev.edges.size());
  ev.rotation_error_deg = rotation_angle_deg(Q.linear());
  ev.translation_error = Q.translation().norm();
  ev.rotation_tolerance_deg = c.rotation_threshold_deg * std::sqrt(k);
  ev.translation_tolerance = std::sqrt(t_var);
  ev.consistent = ev.rotation_error_deg <= ev.rotation_tolerance_deg &&
                  ev.translation_error <= ev.translation_tolerance;
  return ev;
}

double badness(const CycleEvidence& ev) {
  return std::max(ev.rotation_error_deg / ev.rotation_tolerance_deg,
                  ev.translation_error / ev.translation_tolerance);
}

struct EdgeLoops {
  int consistent = 0;
  int inconsistent = 0;
  std::vector<CycleEvidence> open;  // inconsistent loops, worst first
};

std::vector<EdgeLoops> examine(const WorkGraph& g, const ConsistencyConfig& c) {
  std::vector<EdgeLoops> out(g.edges.size());
  LoopFinder finder(g, c);
  for (std::size_t k = 0; k < g.edges.size(); ++k) {
    if (!g.edges[k].active) continue;
    for (const Path& p : finder.loops_through(static_cast<int>(k))) {
      CycleEvidence ev = close_loop(g, static_cast<int>(k), p, c);
      if (ev.consistent) {
        ++out[k].consistent;
      } else {
        ++out[k].inconsistent;
        out[k].open.push_back(std::move(ev));
      }
    }
    std::sort(out[k].open.begin(), out[k].open.end(),
              [](const CycleEvidence& a, const CycleEvidence& b) { return badness(a) > badness(b); });
  }
  return out;
}

void reject(WorkEdge& e, EdgeLoops& loops, const char* rule, const ConsistencyConfig& c) {
  e.active = false;
  EdgeSolution& r = e.report;
  r.state = EdgeState::kRejected;
  r.verified = false;
  r.consistent_cycles = loops.consistent;
  r.inconsistent_cycles = loops.inconsistent;
  const CycleEvidence& worst = loops.open.front();
  char buf[256];
  std::snprintf(buf, sizeof buf,
                "cycle consistency: %s (%d of %d loops open; worst: rotation %.2f deg > %.2f or "
                "translation %.3f m > %.3f)",
                rule, loops.inconsistent, loops.inconsistent + loops.consistent,
                worst.rotation_error_deg, worst.rotation_tolerance_deg, worst.translation_error,
                worst.translation_tolerance);
  r.reason = buf;
  const auto n = std::min<std::size_t>(loops.open.size(), static_cast<std::size_t>(std::max(0, c.max_evidence)));
  r.evidence.assign(loops.open.begin(), loops.open.begin() + static_cast<std::ptrdiff_t>(n));
}

/// One rejection step; false when every loop closes.
bool reject_step(WorkGraph& g, std::vector<EdgeLoops>& loops, const ConsistencyConfig& c) {
  bool any = false;
  for (std::size_t k = 0; k < g.edges.size(); ++k) {  // rule 1: open loops, no support
    if (g.edges[k].active && loops[k].inconsistent > 0 && loops[k].consistent == 0) {
      reject(g.edges[k], loops[k], "no loop through it closes", c);
      any = true;
    }
  }
  if (any) return true;
  int worst = -1;
  auto key = [&](int k) {
    const double share = static_cast<double>(loops[k].inconsistent) /
                         static_cast<double>(loops[k].inconsistent + loops[k].consistent);
    return std::make_tuple(share, loops[k].inconsistent, g.edges[k].tree_cost);
  };
  for (std::size_t k = 0; k < g.edges.size(); ++k) {  // rule 2: the most contradicted edge
    const int i = static_cast<int>(k);
    if (!g.edges[k].active || loops[k].inconsistent == 0) continue;
    if (worst < 0 || key(i) > key(worst)) worst = i;
  }
  if (worst < 0) return false;
  reject(g.edges[worst], loops[worst], "most loops through it do not close", c);
  return true;
}

}  // namespace

void check_consistency(WorkGraph& g, const ConsistencyConfig& c) {
  if (!c.enabled) return;
  std::vector<EdgeLoops> loops = examine(g, c);
  while (reject_step(g, loops, c)) loops = examine(g, c);
  for (std::size_t k = 0; k < g.edges.size(); ++k) {
    if (!g.edges[k].active) continue;
    EdgeSolution& r = g.edges[k].report;
    r.consistent_cycles = loops[k].consistent;
    r.inconsistent_cycles = 0;
    r.verified = loops[k].consistent > 0;
  }
}

}  // namespace mapmerge::graph::detail
