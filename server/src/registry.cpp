#include "mapmerge/server/registry.hpp"

#include <algorithm>
#include <cstdio>
#include <set>
#include <stdexcept>
#include <utility>

#include <spdlog/spdlog.h>

namespace mapmerge::server {
namespace {

/// Information of an alignment edge (graph/information.hpp). A restored edge carries no inlier
/// count or overlap: it is taken as a typical alignment of its fitness.
graph::Matrix6d edge_information(const Edge& e, const graph::InformationConfig& config) {
  if (!e.information.isZero(0.0)) return e.information;  // as computed when the edge was made
  graph::AlignmentQuality q{e.inliers, e.fitness, e.overlap, e.pivot_source};
  if (q.inliers == 0) {
    q.inliers = static_cast<std::size_t>(config.reference_inliers);
    q.overlap = config.reference_overlap;
  }
  graph::EdgeInformation info = graph::information_from_alignment(q, config);
  if (!info.valid) {
    q.fitness = config.min_fitness;
    info = graph::information_from_alignment(q, config);
  }
  return info.information;
}

const char* state_name(graph::EdgeState s) {
  switch (s) {
    case graph::EdgeState::kAccepted: return "accepted";
    case graph::EdgeState::kRejected: return "rejected";
    case graph::EdgeState::kNotConnected: break;
  }
  return "not_connected";
}

/// "loop a|b > b|c > c|a open by 120.31 deg (tol 3.46), 4.210 m (tol 0.310); ..."
std::string evidence_text(const std::vector<graph::CycleEvidence>& loops) {
  std::string out;
  for (const graph::CycleEvidence& c : loops) {
    if (!out.empty()) out += "; ";
    out += "loop";
    for (std::size_t i = 0; i < c.edges.size(); ++i) out += (i == 0 ? " " : " > ") + c.edges[i];
    char buf[160];
    std::snprintf(buf, sizeof buf, " open by %.2f deg (tol %.2f), %.3f m (tol %.3f)", c.rotation_error_deg,
                  c.rotation_tolerance_deg, c.translation_error, c.translation_tolerance);
    out += buf;
  }
  return out;
}

}  // namespace

const char* to_string(RobotStatus status) {
  switch (status) {
    case RobotStatus::kAligned: return "aligned";
    case RobotStatus::kRejected: return "rejected";
    case RobotStatus::kUnknown: break;
  }
  return "unknown";
}

const char* to_string(Admission a) {
  switch (a) {
    case Admission::kNew: return "new";
    case Admission::kNewSession: return "new_session";
    case Admission::kDuplicate: return "duplicate";
    case Admission::kOutOfOrder: return "out_of_order";
    case Admission::kConflict: return "conflict";
  }
  return "?";
}

namespace {

/// RFC 1982 serial number order over 64 bits: `b` is after `a` when it is less than 2^63 ahead.
bool serial_after(std::uint64_t b, std::uint64_t a) { return b != a && b - a < (std::uint64_t{1} << 63); }

constexpr std::size_t kReplacedKept = 8;  ///< replaced sessions remembered per robot

}  // namespace

Admission Registry::admit(const std::string& robot, const std::string& session, std::uint64_t sequence,
                          Clock::time_point now) {
  std::lock_guard<std::mutex> lock(mutex_);
  auto it = seen_.find(robot);
  if (it == seen_.end()) {
    Seen& s = seen_[robot];
    s.session = session;
    s.sequence = sequence;
    s.last = now;
    return Admission::kNew;
  }
  Seen& s = it->second;
  if (s.session != session) {
    const auto replaced = std::find(s.replaced.begin(), s.replaced.end(), session);
    const bool in_force = now - s.last < std::chrono::duration<double>(conflict_hold_s_);
    if (replaced != s.replaced.end() && in_force) return Admission::kConflict;
    if (replaced != s.replaced.end()) s.replaced.erase(replaced);
    s.replaced.push_back(s.session);
    if (s.replaced.size() > kReplacedKept) s.replaced.erase(s.replaced.begin());
    s.warned.erase(session);
    s.session = session;
    s.sequence = sequence;
    s.last = now;
    return Admission::kNewSession;
  }
  s.last = now;  // the session in force still publishes, also when it repeats itself
  if (sequence == s.sequence) {
    ++s.ignored;
    return Admission::kDuplicate;
  }
  if (!serial_after(sequence, s.sequence)) {
    ++s.ignored;
    return Admission::kOutOfOrder;
  }
  s.sequence = sequence;
  return Admission::kNew;
}

void Registry::set_conflict_hold(double seconds) {
  std::lock_guard<std::mutex> lock(mutex_);
  conflict_hold_s_ = seconds;
}

std::uint64_t Registry::ignored(const std::string& robot) const {
  std::lock_guard<std::mutex> lock(mutex_);
  const auto it = seen_.find(robot);
  return it == seen_.end() ? 0 : it->second.ignored;
}

std::string Registry::session_of(const std::string& robot) const {
  std::lock_guard<std::mutex> lock(mutex_);
  const auto it = seen_.find(robot);
  return it == seen_.end() ? std::string() : it->second.session;
}

bool Registry::first_conflict(const std::string& robot, const std::string& session) {
  std::lock_guard<std::mutex> lock(mutex_);
  auto it = seen_.find(robot);
  return it != seen_.end() && it->second.warned.insert(session).second;
}

std::uint64_t Registry::next_sequence(const std::string& robot, const std::string& session) const {
  std::lock_guard<std::mutex> lock(mutex_);
  const auto it = seen_.find(robot);
  return it == seen_.end() || it->second.session != session ? 1 : it->second.sequence + 1;
}

RobotRecord& Registry::mutable_record(const std::string& robot) {
  auto& slot = records_[robot];
  slot = slot ? std::make_shared<RobotRecord>(*slot) : std::make_shared<RobotRecord>();
  slot->robot_id = robot;
  return *slot;
}

void Registry::put_map(RobotRecord record) {
  std::lock_guard<std::mutex> lock(mutex_);
  RobotRecord& r = mutable_record(record.robot_id);
  if (!r.session_id.empty() && r.session_id != record.session_id) {
    // A new session may come with a new map frame: its alignments no longer hold.
    for (auto it = edges_.begin(); it != edges_.end();) {
      const bool involved = it->first.first == r.robot_id || it->first.second == r.robot_id;
      it = involved ? edges_.erase(it) : std::next(it);
    }
    graph_stale_ = true;
  }
  record.map_revision = r.map_revision + 1;
  record.updates_accepted = r.updates_accepted + 1;
  record.updates_rejected = r.updates_rejected;
  record.last_error = r.last_error;
  record.tried.clear();
  auto& s = seen_[record.robot_id];
  if (s.session.empty()) {
    s = Seen{};
    s.session = record.session_id;
    s.sequence = record.sequence;
  }
  r = std::move(record);
}

bool Registry::touch_if_unchanged(const std::string& robot, const std::string& session, std::uint64_t sequence,
                                  std::size_t content_hash, double received_unix) {
  std::lock_guard<std::mutex> lock(mutex_);
  const auto it = records_.find(robot);
  if (it == records_.end()) return false;
  const RobotRecord& held = *it->second;
  if (!held.map || held.session_id != session || held.content_hash != content_hash) return false;
  RobotRecord& r = mutable_record(robot);  // copy on write: readers keep their snapshot
  r.sequence = sequence;
  r.received_unix = received_unix;
  ++r.updates_accepted;
  return true;
}

void Registry::reject(const std::string& robot, const std::string& reason) {
  std::lock_guard<std::mutex> lock(mutex_);
  RobotRecord& r = mutable_record(robot);
  ++r.updates_rejected;
  r.last_error = reason;
}

void Registry::set_prepared(const std::string& robot, std::uint64_t revision,
                            std::shared_ptr<const align::PreparedMap> prepared) {
  std::lock_guard<std::mutex> lock(mutex_);
  auto it = records_.find(robot);
  if (it == records_.end() || it->second->map_revision != revision) return;
  mutable_record(robot).prepared = std::move(prepared);
}

void Registry::mark_tried(const std::string& robot, std::uint64_t revision, const std::string& other) {
  std::lock_guard<std::mutex> lock(mutex_);
  auto it = records_.find(robot);
  if (it == records_.end() || it->second->map_revision != revision) return;
  mutable_record(robot).tried.insert(other);
}

void Registry::note_alignment_use(const std::string& robot, Clock::time_point now) {
  std::lock_guard<std::mutex> lock(mutex_);
  Clock::time_point& t = alignment_use_[robot];
  t = std::max(t, now);
}

Registry::AlignmentUse::AlignmentUse(Registry& registry, std::string robot)
    : registry_(registry), robot_(std::move(robot)) {
  std::lock_guard<std::mutex> lock(registry_.mutex_);
  ++registry_.alignment_holds_[robot_];
}

Registry::AlignmentUse::~AlignmentUse() {
  registry_.note_alignment_use(robot_);  // before the hold ends: never idle in between
  std::lock_guard<std::mutex> lock(registry_.mutex_);
  if (--registry_.alignment_holds_[robot_] == 0) registry_.alignment_holds_.erase(robot_);
}

bool Registry::alignment_data_idle_locked(const std::string& robot, const RobotRecord& rec,
                                          Clock::time_point cutoff) const {
  if (!rec.map || (!rec.prepared && !(rec.map->has_body() && rec.map->has_tree()))) return false;
  if (alignment_holds_.count(robot) != 0) return false;
  const auto used = alignment_use_.find(robot);
  return used == alignment_use_.end() || used->second < cutoff;
}

std::vector<std::string> Registry::idle_alignment_data(Clock::time_point cutoff) const {
  std::lock_guard<std::mutex> lock(mutex_);
  std::vector<std::string> idle;
  for (const auto& [id, rec] : records_) {
    if (alignment_data_idle_locked(id, *rec, cutoff)) idle.push_back(id);
  }
  return idle;
}

std::vector<std::string> Registry::release_alignment_data(Clock::time_point cutoff) {
  std::vector<std::shared_ptr<const align::PreparedMap>> freed;  // freed after the lock is let go of
  std::vector<std::shared_ptr<const HeldMap>> maps;
  std::vector<std::string> released;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    for (const auto& [id, rec] : records_) {
      if (!alignment_data_idle_locked(id, *rec, cutoff)) continue;
      maps.push_back(rec->map);
      released.push_back(id);
    }
    for (const std::string& id : released) {
      if (records_.at(id)->prepared) freed.push_back(std::exchange(mutable_record(id).prepared, nullptr));
    }
  }
  freed.clear();
  // An octree built from a map's bytes for another use (an export) goes too.
  for (const auto& map : maps) map->release_tree();
  return released;
}

void Registry::put_edge(const Edge& edge) {
  std::lock_guard<std::mutex> lock(mutex_);
  edges_.erase({edge.source, edge.target});
  edges_[{edge.target, edge.source}] = edge;
  graph_stale_ = true;
}

std::vector<Edge> Registry::edges() const {
  std::lock_guard<std::mutex> lock(mutex_);
  std::vector<Edge> out;
  for (const auto& kv : edges_) out.push_back(kv.second);
  return out;
}

std::vector<Edge> Registry::edges_of(const std::string& robot) const {
  std::vector<Edge> out;
  for (const Edge& e : edges()) {
    if (e.target == robot || e.source == robot) out.push_back(e);
  }
  return out;
}

std::string Registry::reference() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return reference_;
}

std::string Registry::claim_reference(const std::string& robot) {
  std::lock_guard<std::mutex> lock(mutex_);
  if (reference_.empty()) reference_ = robot;
  return reference_;
}

std::shared_ptr<const RobotRecord> Registry::get(const std::string& robot) const {
  std::lock_guard<std::mutex> lock(mutex_);
  auto it = records_.find(robot);
  return it == records_.end() ? nullptr : it->second;
}

std::vector<std::shared_ptr<const RobotRecord>> Registry::all() const {
  std::lock_guard<std::mutex> lock(mutex_);
  std::vector<std::shared_ptr<const RobotRecord>> out;
  for (const auto& kv : records_) out.push_back(kv.second);
  return out;
}

std::map<std::string, GlobalPose> Registry::composed_poses_locked() const {
  std::vector<Edge> usable;
  for (const auto& kv : edges_) usable.push_back(kv.second);
  return global_poses(reference_, usable);
}

graph::GraphSolution Registry::solve_locked() const {
  if (graph_.reference() != reference_ && !reference_.empty()) graph_.set_reference(reference_);
  if (graph_stale_) {
    std::set<std::string> current;
    for (const auto& kv : edges_) {
      const Edge& e = kv.second;
      graph::Edge g;
      g.source = e.source;
      g.target = e.target;
      g.T_target_source = Eigen::Isometry3d(e.T_target_source);
      g.information = edge_information(e, graph::InformationConfig{});
      try {
        current.insert(graph_.add_or_update_edge(g));
      } catch (const std::invalid_argument& ex) {
        spdlog::warn("pose graph: edge {} <- {} left out: {}", e.target, e.source, ex.what());
      }
    }
    std::vector<std::string> stale;
    for (const auto& kv : graph_.edges()) {
      if (current.count(kv.first) == 0) stale.push_back(kv.first);
    }
    for (const auto& id : stale) graph_.remove_edge(id);
    graph_stale_ = false;
  }
  return graph_.optimise(graph_config_);
}

std::map<std::string, GlobalPose> Registry::poses_locked() const {
  const auto composed = composed_poses_locked();
  std::map<std::string, GlobalPose> poses;
  const graph::GraphSolution solution = solve_locked();
  if (!solution.valid) {
    poses = composed;  // fallback: the spanning-tree composition
  } else {
    for (const graph::RobotSolution& r : solution.robots) {
      if (!r.connected) continue;  // all its edges rejected, or none: POSE_UNKNOWN, not fused
      GlobalPose p;
      p.T_global_robot = r.T_global_robot.matrix();
      p.quality = r.quality;
      if (auto c = composed.find(r.id); c != composed.end()) {
        p.fitness = c->second.fitness;
        p.hops = c->second.hops;
      }
      poses[r.id] = p;
    }
  }
  for (auto it = poses.begin(); it != poses.end();) {
    auto rec = records_.find(it->first);
    const bool has_map = rec != records_.end() && rec->second->map != nullptr;
    it = has_map ? std::next(it) : poses.erase(it);
  }
  return poses;
}

std::vector<EdgeVerdict> Registry::edge_verdicts() const {
  std::lock_guard<std::mutex> lock(mutex_);
  const graph::GraphSolution solution = solve_locked();
  std::vector<EdgeVerdict> out;
  for (const auto& kv : edges_) {
    const Edge& e = kv.second;
    EdgeVerdict v{e.target, e.source, "not_connected", "", ""};
    if (const graph::EdgeSolution* g = solution.edge(graph::default_edge_id(e.source, e.target))) {
      v.state = state_name(g->state);
      v.reason = g->reason;
      v.evidence = evidence_text(g->evidence);
    } else if (!solution.valid) {
      v.reason = solution.reason;
    }
    out.push_back(std::move(v));
  }
  return out;
}

std::vector<EdgeVerdict> Registry::rejected_edges() const {
  std::vector<EdgeVerdict> out;
  for (EdgeVerdict& v : edge_verdicts()) {
    if (v.state == "rejected") out.push_back(std::move(v));
  }
  return out;
}

std::map<std::string, GlobalPose> Registry::poses() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return poses_locked();
}

RobotStatus Registry::status(const std::string& robot) const {
  std::lock_guard<std::mutex> lock(mutex_);
  if (poses_locked().count(robot) != 0) return RobotStatus::kAligned;
  auto it = records_.find(robot);
  if (it != records_.end() && it->second->map == nullptr && it->second->updates_rejected > 0) {
    return RobotStatus::kRejected;
  }
  return RobotStatus::kUnknown;
}

bool Registry::set_alive(const std::string& robot, bool alive) {
  std::lock_guard<std::mutex> lock(mutex_);
  Presence& p = presence_[robot];
  if (p.alive == alive) return false;
  p.alive = alive;
  if (!alive) ++p.times_lost;
  return true;
}

Registry::Presence Registry::presence(const std::string& robot) const {
  std::lock_guard<std::mutex> lock(mutex_);
  const auto it = presence_.find(robot);
  return it == presence_.end() ? Presence{} : it->second;
}

}  // namespace mapmerge::server
