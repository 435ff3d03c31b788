#include "mapmerge/server/pipeline.hpp"

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cmath>
#include <string_view>

#include <malloc.h>

#include <spdlog/spdlog.h>

#include "mapmerge/server/merge_ops.hpp"

namespace mapmerge::server {
namespace {

constexpr std::size_t kRecentMerges = 16;  ///< merge reports kept for the status topic

double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

/// How a global search remembers a failed partner: until the searching robot's map changes, or
/// the partner's map does.
std::string tried_key(const RobotRecord& other) {
  return other.robot_id + "#" + std::to_string(other.map_revision);
}

std::pair<std::string, std::string> ordered(const std::string& a, const std::string& b) {
  return a < b ? std::make_pair(a, b) : std::make_pair(b, a);
}

constexpr double kOverlapReuseDeg = 5.0;  ///< an overlap estimate holds while the pair's relative pose moves less [deg]
constexpr double kOverlapReuseM = 0.5;    ///< ... and less than this [m]

/// What a pair try is remembered by, per robot: its map's bytes and its session (a new session
/// may bring a new map frame, so tries of the old one say nothing; its alignments are dropped too).
std::uint64_t try_identity(const RobotRecord& r) {
  return static_cast<std::uint64_t>(r.content_hash) ^
         (static_cast<std::uint64_t>(std::hash<std::string>{}(r.session_id)) * 0x9E3779B97F4A7C15ULL);
}

std::size_t content_hash(const MapSample& m) {
  return std::hash<std::string_view>{}(
      std::string_view(reinterpret_cast<const char*>(m.data.data()), m.data.size()));
}

}  // namespace

Pipeline::Pipeline(const ServerConfig& config, Registry& registry, Store* store, Hooks hooks)
    : config_(config), registry_(registry), store_(store), hooks_(std::move(hooks)) {}

void Pipeline::process(const std::string& robot, std::optional<MapSample> map, bool retry) {
  const auto job_of = [&](const std::string& suffix) {
    return robot.size() > suffix.size() && robot.compare(robot.size() - suffix.size(), suffix.size(), suffix) == 0;
  };
  if (robot == release_job()) return release_turn();
  if (job_of(refine_job(""))) return refine_turn(robot.substr(0, robot.size() - refine_job("").size()));
  if (job_of(search_job(""))) return search_turn(robot.substr(0, robot.size() - search_job("").size()));
  if (map && unchanged(*map)) {
    // The same map again (a periodic republish): only partners whose maps changed since are
    // worth a new global search; an aligned robot needs nothing.
    spdlog::debug("robot {}: map {}/{} unchanged", robot, map->session_id, map->sequence);
    if (registry_.status(robot) != RobotStatus::kAligned) place(robot);
    return;
  }
  if (map) {
    if (!ingest(*map, true)) return;
  } else if (!retry || registry_.status(robot) == RobotStatus::kAligned) {
    return;
  }
  place(robot);
}

bool Pipeline::restore(const MapSample& map) { return ingest(map, false); }

bool Pipeline::unchanged(const MapSample& m) {
  const auto held = registry_.get(m.topic_robot);
  if (!held || !held->map || held->session_id != m.session_id || held->content_hash != content_hash(m)) return false;
  // Stored before the registry shows it (the status topic reports the registry's sequence).
  if (store_ != nullptr) store_->touch_map(m.topic_robot, m.session_id, m.sequence, m.received_unix);
  return registry_.touch_if_unchanged(m.topic_robot, m.session_id, m.sequence, content_hash(m), m.received_unix);
}

bool Pipeline::ingest(const MapSample& m, bool persist) {
  const std::string& robot = m.topic_robot;
  const auto t0 = std::chrono::steady_clock::now();
  DecodedMap decoded = decode_sample(m, config_.limits);
  const double decode_s = seconds_since(t0);
  if (!decoded.map) {
    ++rejected_;
    registry_.reject(robot, decoded.reason);
    spdlog::warn("robot {}: update {}/{} rejected: {}", robot, m.session_id, m.sequence, decoded.reason);
    return false;
  }
  RobotRecord r;
  r.robot_id = robot;
  r.session_id = m.session_id;
  r.sequence = m.sequence;
  r.frame_id = m.frame_id.empty() ? robot + "/map" : m.frame_id;
  r.resolution = decoded.map->resolution();
  r.received_unix = m.received_unix;
  r.map = decoded.map;
  r.content_hash = content_hash(m);
  const std::size_t nodes = decoded.map->num_nodes();
  warn_on_resolution(robot, r.resolution);
  // Stored before the registry (and so the status topic and the global map) shows it: what the
  // server has published is never lost by a crash. A failed write keeps the map in memory.
  const auto t1 = std::chrono::steady_clock::now();
  const auto held = registry_.get(robot);
  const bool new_session = held && !held->session_id.empty() && held->session_id != m.session_id;
  // A new session may come with a new map frame: its stored alignments go first (the registry
  // drops them in put_map).
  if (persist && new_session) store_edges_without(robot);
  if (persist && store_ != nullptr && !store_->save_map(m)) {
    spdlog::error("robot {}: map {}/{} served from memory only until the store works again", robot, m.session_id,
                  m.sequence);
  }
  // A new session not while an alignment of the old one installs its edge (accept_edge checks).
  std::unique_lock<std::mutex> lock(alignment_mutex_, std::defer_lock);
  if (new_session) lock.lock();
  registry_.put_map(std::move(r));
  if (lock.owns_lock()) lock.unlock();
  ++accepted_;
  spdlog::info("robot {}: map {}/{} accepted ({} nodes, {:.3f} m; check {:.0f} ms, store {:.0f} ms)", robot,
               m.session_id, m.sequence, nodes, decoded.map->resolution(), decode_s * 1e3, seconds_since(t1) * 1e3);
  return true;
}

void Pipeline::warn_on_resolution(const std::string& robot, double resolution) const {
  const auto ref = registry_.get(registry_.reference());
  if (ref && ref->map && ref->robot_id != robot && std::abs(ref->resolution - resolution) > 1e-9) {
    spdlog::warn("robot {}: resolution {:.3f} m differs from the reference's {:.3f} m: fusion resamples it", robot,
                 resolution, ref->resolution);
  }
}

void Pipeline::place(const std::string& robot) {
  const auto rec = registry_.get(robot);
  if (!rec || !rec->map) return;
  const std::string wanted = config_.merge.reference.empty() ? robot : config_.merge.reference;
  const std::string reference = registry_.claim_reference(wanted);
  if (robot == reference) {
    if (rec->map_revision == 1) {
      spdlog::info("robot {} defines the global frame", robot);
      store_edges_without("");  // stores the reference
    }
    // Robots heard before the reference (or dropped by its new session) wait for this; the
    // retry is a no-op for robots already tried against it.
    on_new_alignment(robot, true);
    return;
  }
  if (registry_.poses().count(robot) != 0) {
    // A growing map keeps its frame: fuse it at once with the known transform, then polish the
    // transform locally and republish only if that moved the robot noticeably.
    if (hooks_.changed) hooks_.changed();
    if (hooks_.more_idle_work) hooks_.more_idle_work();  // its extra pairs are worth a new try
    if (!config_.merge.refine_known) return;
    if (hooks_.refine) {
      hooks_.refine(refine_job(robot));
    } else if (refine_known(*rec)) {
      on_new_alignment(robot, false);
    }
    return;
  }
  if (hooks_.search) {
    hooks_.search(search_job(robot));
  } else {
    search_unknown(*rec);
  }
}

void Pipeline::search_turn(const std::string& robot) {
  const auto rec = registry_.get(robot);  // the latest map: a search of an older one is moot
  if (!rec || !rec->map || registry_.poses().count(robot) != 0 || robot == registry_.reference()) return;
  search_unknown(*rec);
}

void Pipeline::refine_turn(const std::string& robot) {
  const auto rec = registry_.get(robot);  // the latest map: earlier ones need no refinement
  if (!rec || !rec->map || registry_.poses().count(robot) == 0 || robot == registry_.reference()) return;
  if (refine_known(*rec)) on_new_alignment(robot, false);
}

Registry::Clock::time_point Pipeline::alignment_data_cutoff() const {
  return Registry::Clock::now() - std::chrono::duration_cast<Registry::Clock::duration>(
                                      std::chrono::duration<double>(config_.merge.alignment_data_hold_s));
}

bool Pipeline::alignment_data_idle() const { return !registry_.idle_alignment_data(alignment_data_cutoff()).empty(); }

void Pipeline::release_turn() {
  const auto released = registry_.release_alignment_data(alignment_data_cutoff());
  if (released.empty()) return;
  malloc_trim(0);  // the clouds' and kd-trees' pages back to the system (~5 ms; on a merge thread)
  std::string who;
  for (const auto& id : released) who += " " + id;
  spdlog::debug("alignment data of{} let go of: not used for {:.0f} s", who, config_.merge.alignment_data_hold_s);
}

std::shared_ptr<const align::PreparedMap> Pipeline::prepared(const std::string& robot, bool features) {
  const auto rec = registry_.get(robot);
  if (!rec || !rec->map) return nullptr;
  if (rec->prepared && (!features || rec->prepared->has_features())) return rec->prepared;
  std::string error;
  const auto t0 = std::chrono::steady_clock::now();
  // Read off the map's bytes: its octree (~57 B a node) is not built.
  const auto p = prepare(*rec->map, config_.align, features, error);
  spdlog::debug("robot {}: map prepared ({}) in {:.0f} ms", robot, features ? "features" : "refine only",
                seconds_since(t0) * 1e3);
  if (!p) {
    spdlog::warn("robot {}: map cannot be aligned: {}", robot, error);
    return nullptr;
  }
  registry_.set_prepared(robot, rec->map_revision, p);
  return p;
}

void Pipeline::search_unknown(const RobotRecord& rec) {
  const Registry::AlignmentUse hold_me(registry_, rec.robot_id);
  const auto me = prepared(rec.robot_id, true);
  if (!me) return;
  std::vector<std::shared_ptr<const RobotRecord>> candidates;
  for (const auto& [id, pose] : registry_.poses()) {
    auto other = registry_.get(id);
    if (id != rec.robot_id && other && rec.tried.count(tried_key(*other)) == 0 && !attempted(rec, *other, "search")) {
      candidates.push_back(other);
    }
  }
  // Robots this one was never refused against come first (a pair refused before, with older
  // maps, likely overlaps little: a robot aligned since then must not wait behind its retry),
  // then the largest maps.
  std::vector<std::pair<bool, std::shared_ptr<const RobotRecord>>> order;
  for (const auto& other : candidates) order.emplace_back(refused_before(rec, *other, "search"), other);
  std::stable_sort(order.begin(), order.end(), [](const auto& a, const auto& b) {
    return a.first != b.first ? !a.first : a.second->map->num_nodes() > b.second->map->num_nodes();
  });
  // A search stopped by the shutdown is neither reported nor remembered as tried.
  const align::Cancel on_shutdown = [this] { return stopping(); };
  for (const auto& [refused, other] : order) {
    if (stopping()) return;
    const Registry::AlignmentUse hold_target(registry_, other->robot_id);
    const auto target = prepared(other->robot_id, true);
    if (!target) continue;
    spdlog::info("merge {} <- {}: global search started", other->robot_id, rec.robot_id);
    auto t0 = std::chrono::steady_clock::now();
    align::AlignResult res = align_global(*target, *me, config_.align, on_shutdown);
    if (stopping()) return;
    report({other->robot_id, rec.robot_id, res.accepted, true, res.fitness, seconds_since(t0), res.reason, unix_now()});
    if (!res.accepted && config_.merge.search_blocks_fallback && !config_.align.submodels.enabled) {
      align::AlignConfig blocks = config_.align;
      blocks.submodels.enabled = true;
      spdlog::info("merge {} <- {}: global search again, block by block", other->robot_id, rec.robot_id);
      t0 = std::chrono::steady_clock::now();
      res = align_global(*target, *me, blocks, on_shutdown);
      if (stopping()) return;
      report({other->robot_id, rec.robot_id, res.accepted, true, res.fitness, seconds_since(t0), res.reason,
              unix_now()});
    }
    registry_.mark_tried(rec.robot_id, rec.map_revision, tried_key(*other));
    record_attempt(rec, *other, "search", res.accepted, res.reason);
    if (res.accepted) {
      if (accept_edge(make_edge(*other, rec, res), *other, rec)) on_new_alignment(rec.robot_id, true);
      return;
    }
  }
  if (!order.empty() && hooks_.more_idle_work) hooks_.more_idle_work();  // rescues of the refusals
}

bool Pipeline::worth_refining(const Edge& edge) {
  const auto target = registry_.get(edge.target), source = registry_.get(edge.source);
  if (!target || !target->map || !source || !source->map) return false;
  std::lock_guard<std::mutex> lock(alignment_mutex_);
  const auto basis = edge_basis_.find({edge.target, edge.source});
  if (basis == edge_basis_.end()) return true;  // aligned before a restart: not known
  const auto changed = [&](std::size_t now, std::size_t then) {
    const double d = std::abs(static_cast<double>(now) - static_cast<double>(then));
    return d > 0.0 && d >= config_.merge.refine_min_change * static_cast<double>(std::max<std::size_t>(then, 1));
  };
  return changed(target->map->num_nodes(), basis->second.first) ||
         changed(source->map->num_nodes(), basis->second.second);
}

bool Pipeline::refine_known(const RobotRecord& rec) {
  // The robot's own links to the group: edges where its map is the source. Edges of robots
  // aligned to it keep their transform (a growing map does not move its frame).
  std::vector<Edge> edges;
  for (const Edge& e : registry_.edges_of(rec.robot_id)) {
    if (e.source != rec.robot_id) continue;
    if (worth_refining(e)) {
      edges.push_back(e);
    } else {
      spdlog::debug("merge {} <- {}: maps changed by less than {:.0f}% since aligned: not refined", e.target,
                    e.source, config_.merge.refine_min_change * 100.0);
    }
  }
  if (edges.empty()) return false;
  const Registry::AlignmentUse hold_me(registry_, rec.robot_id);
  const auto me = prepared(rec.robot_id, false);
  if (!me) return false;
  bool moved = false;
  bool refined = false;
  for (const Edge& e : edges) {
    const Registry::AlignmentUse hold_target(registry_, e.target);
    const auto target = prepared(e.target, false);
    if (!target) continue;
    spdlog::debug("merge {} <- {}: refinement started", e.target, e.source);
    const auto t0 = std::chrono::steady_clock::now();
    const align::AlignResult res = align_local(*target, *me, e.T_target_source, config_.align);
    report({e.target, e.source, res.accepted, false, res.fitness, seconds_since(t0), res.reason, unix_now()});
    if (!res.accepted) continue;
    const auto target_rec = registry_.get(e.target);
    if (!target_rec || !accept_edge(make_edge(*target_rec, rec, res), *target_rec, rec)) continue;
    refined = true;
    moved |= moved_noticeably(e.T_target_source, res.T_target_source);
  }
  if (refined && !moved) persist_edges();  // moved: on_new_alignment persists
  return moved;
}

bool Pipeline::moved_noticeably(const Eigen::Matrix4d& before, const Eigen::Matrix4d& after) const {
  return server::moved_noticeably(before, after, config_.merge.refine_republish_translation,
                                  config_.merge.refine_republish_rotation_deg);
}

void Pipeline::persist_edges() {
  if (store_ == nullptr) return;
  std::lock_guard<std::mutex> lock(alignment_mutex_);
  store_->save_alignment(registry_.reference(), registry_.edges(), registry_.edge_verdicts());  // logs failures
}

bool Pipeline::accept_edge(const Edge& edge, const RobotRecord& target, const RobotRecord& source) {
  // Stored before the registry (and so the published poses) shows it; one edge set at a time.
  std::lock_guard<std::mutex> lock(alignment_mutex_);
  for (const RobotRecord* r : {&target, &source}) {
    // Aligned on a map of a session that ended meanwhile (its frame may be another).
    const auto now = registry_.get(r->robot_id);
    if (!now || now->session_id != r->session_id) {
      spdlog::info("merge {} <- {}: dropped: robot {} started a new session during the alignment", edge.target,
                   edge.source, r->robot_id);
      return false;
    }
  }
  if (store_ != nullptr) {
    std::vector<Edge> edges;
    for (const Edge& e : registry_.edges()) {
      const bool same_pair = (e.target == edge.target && e.source == edge.source) ||
                             (e.target == edge.source && e.source == edge.target);
      if (!same_pair) edges.push_back(e);
    }
    edges.push_back(edge);
    if (!store_->save_alignment(registry_.reference(), edges, registry_.edge_verdicts())) {
      spdlog::error("alignment {} <- {} served from memory only until the store works again", edge.target,
                    edge.source);
    }
  }
  registry_.put_edge(edge);
  const auto target_now = registry_.get(edge.target), source_now = registry_.get(edge.source);
  if (target_now && target_now->map && source_now && source_now->map) {
    edge_basis_[{edge.target, edge.source}] = {target_now->map->num_nodes(), source_now->map->num_nodes()};
  }
  return true;
}

void Pipeline::store_edges_without(const std::string& robot) {
  if (store_ == nullptr) return;
  std::lock_guard<std::mutex> lock(alignment_mutex_);
  std::vector<Edge> edges;
  for (const Edge& e : registry_.edges()) {
    if (e.target != robot && e.source != robot) edges.push_back(e);
  }
  store_->save_alignment(registry_.reference(), edges, registry_.edge_verdicts());
}

void Pipeline::on_new_alignment(const std::string& robot, bool joined) {
  persist_edges();  // the graph's verdicts of the new edge set
  if (hooks_.changed) hooks_.changed();
  if (hooks_.more_idle_work) hooks_.more_idle_work();
  if (!joined) return;  // the aligned group did not grow: nothing new to try the others against
  const auto poses = registry_.poses();
  for (const auto& r : registry_.all()) {
    if (r->robot_id != robot && r->map && poses.count(r->robot_id) == 0 && hooks_.retry) hooks_.retry(r->robot_id);
  }
}

void Pipeline::report(MergeReportOut r) {
  ++merges_;
  spdlog::info("merge {} <- {} ({}): {} fitness {:.4f} m in {:.2f} s{}{}", r.target, r.source,
               r.global_search ? "global" : "refine", r.accepted ? "accepted" : "rejected", r.fitness,
               r.duration_s, r.detail.empty() ? "" : ": ", r.detail);
  std::lock_guard<std::mutex> lock(reports_mutex_);
  reports_.push_back(std::move(r));
  while (reports_.size() > kRecentMerges) reports_.pop_front();
}

PipelineCounters Pipeline::counters() const {
  return {accepted_.load(),    rejected_.load(),      merges_.load(),           extra_tried_.load(),
          extra_added_.load(), rescues_tried_.load(), rescues_accepted_.load()};
}

// ---- pairs tried -------------------------------------------------------------------------

bool Pipeline::refused_before(const RobotRecord& a, const RobotRecord& b, const std::string& kind) const {
  const auto [first_id, second_id] = ordered(a.robot_id, b.robot_id);
  std::lock_guard<std::mutex> lock(pairs_mutex_);
  const auto it = attempts_.find(first_id + "|" + second_id + "|" + kind);
  return it != attempts_.end() && !it->second.accepted;
}

std::optional<PairAttempt> Pipeline::attempt_now(const RobotRecord& a, const RobotRecord& b,
                                                 const std::string& kind) const {
  const auto [first_id, second_id] = ordered(a.robot_id, b.robot_id);
  std::lock_guard<std::mutex> lock(pairs_mutex_);
  const auto it = attempts_.find(first_id + "|" + second_id + "|" + kind);
  if (it == attempts_.end()) return std::nullopt;
  const RobotRecord& first = a.robot_id < b.robot_id ? a : b;
  const RobotRecord& second = a.robot_id < b.robot_id ? b : a;
  if (it->second.hash_a != try_identity(first) || it->second.hash_b != try_identity(second)) return std::nullopt;
  return it->second;
}

bool Pipeline::attempted(const RobotRecord& a, const RobotRecord& b, const std::string& kind) const {
  return attempt_now(a, b, kind).has_value();
}

void Pipeline::record_attempt(const RobotRecord& a, const RobotRecord& b, const std::string& kind, bool accepted,
                              const std::string& reason) {
  const RobotRecord& first = a.robot_id < b.robot_id ? a : b;
  const RobotRecord& second = a.robot_id < b.robot_id ? b : a;
  const PairAttempt attempt{first.robot_id, second.robot_id, kind, try_identity(first), try_identity(second),
                            accepted, reason, unix_now()};
  {
    std::lock_guard<std::mutex> lock(pairs_mutex_);
    attempts_[attempt.robot_a + "|" + attempt.robot_b + "|" + kind] = attempt;
  }
  if (store_ == nullptr) return;
  try {
    store_->save_attempt(attempt);
  } catch (const StoreError& e) {
    spdlog::error("pair {}-{}: try kept in memory only, store failed: {}", attempt.robot_a, attempt.robot_b, e.what());
  }
}

void Pipeline::restore_attempts(const std::vector<PairAttempt>& attempts) {
  std::lock_guard<std::mutex> lock(pairs_mutex_);
  for (const PairAttempt& a : attempts) attempts_[a.robot_a + "|" + a.robot_b + "|" + a.kind] = a;
}

// ---- idle work: rescues, then extra pairs ---------------------------------------------------

Pipeline::PairClaim::~PairClaim() {
  std::lock_guard<std::mutex> lock(pipeline_.pairs_mutex_);
  pipeline_.in_progress_.erase(ordered(a_, b_));
}

bool Pipeline::stopping() const { return hooks_.cancelled && hooks_.cancelled(); }

std::optional<Pipeline::RecordPair> Pipeline::current_records(const PairJob& job) const {
  auto t = registry_.get(job.target);
  auto s = registry_.get(job.source);
  if (!t || !s || t->map_revision != job.target_revision || s->map_revision != job.source_revision) return std::nullopt;
  return RecordPair{std::move(t), std::move(s)};
}

std::function<void()> Pipeline::next_idle_work() {
  if (std::function<void()> job = next_rescue()) return job;
  return next_extra_pair();
}

std::function<void()> Pipeline::next_rescue() {
  // With align.rescue.enabled every global search ran the rescue's search already.
  if (!config_.merge.idle_rescue || config_.align.rescue.enabled || stopping()) return {};
  std::optional<PairJob> pair = pick_rescue();
  if (!pair) return {};
  return [this, p = *pair] { run_rescue(p); };
}

std::optional<Pipeline::PairJob> Pipeline::pick_rescue() {
  const auto poses = registry_.poses();
  const std::string reference = registry_.reference();
  const double now = unix_now();
  std::vector<std::shared_ptr<const RobotRecord>> aligned;
  for (const auto& kv : poses) {
    if (auto r = registry_.get(kv.first); r && r->map) aligned.push_back(r);
  }
  // The largest partner first, as search_unknown() orders them.
  std::stable_sort(aligned.begin(), aligned.end(),
                   [](const auto& a, const auto& b) { return a->map->num_nodes() > b->map->num_nodes(); });
  for (const auto& rec : registry_.all()) {
    if (!rec->map || rec->robot_id == reference || poses.count(rec->robot_id) != 0) continue;
    for (const auto& other : aligned) {
      // Only a search refused with both maps as they are now, long enough ago (a map that still
      // grows is searched again with more data), and not as ambiguous.
      const std::optional<PairAttempt> search = attempt_now(*rec, *other, "search");
      if (!search || search->accepted || align::ambiguous_refusal(search->reason) ||
          now - search->stamp_unix < config_.merge.idle_rescue_after_s)
        continue;
      if (attempted(*rec, *other, "rescue")) continue;
      std::lock_guard<std::mutex> lock(pairs_mutex_);
      if (!in_progress_.insert(ordered(rec->robot_id, other->robot_id)).second) continue;  // another worker's
      return PairJob{other->robot_id, rec->robot_id, other->map_revision, rec->map_revision};
    }
  }
  return std::nullopt;
}

void Pipeline::run_rescue(const PairJob& p) {
  const PairClaim claim(*this, p.target, p.source);
  const Registry::AlignmentUse hold_target(registry_, p.target), hold_source(registry_, p.source);
  const auto target = prepared(p.target, true);
  const auto source = prepared(p.source, true);
  if (!target || !source || stopping()) return;
  spdlog::info("merge {} <- {}: rescue: global search on denser features (the search refused it)", p.target, p.source);
  const auto t0 = std::chrono::steady_clock::now();
  // Given up when the server stops or a map changes (its new search comes first).
  const align::AlignResult res =
      align_rescue(*target, *source, config_.align, [&] { return stopping() || !current_records(p); });
  const auto records = current_records(p);
  if (stopping() || !records) {
    spdlog::info("merge {} <- {}: rescue given up after {:.1f} s: {}", p.target, p.source, seconds_since(t0),
                 records ? "the server stops" : "a map changed");
    return;
  }
  report({p.target, p.source, res.accepted, true, res.fitness, seconds_since(t0),
          "rescue" + (res.accepted ? std::string() : ": " + res.reason), unix_now()});
  ++rescues_tried_;
  const auto& [t, s] = *records;
  record_attempt(*t, *s, "rescue", res.accepted, res.reason);
  if (!res.accepted) return;
  ++rescues_accepted_;
  if (accept_edge(make_edge(*t, *s, res), *t, *s)) on_new_alignment(p.source, true);
}

// ---- extra pairs (idle work) -------------------------------------------------------------

std::function<void()> Pipeline::next_extra_pair() {
  if (!config_.merge.extra_pairs || stopping()) return {};
  std::optional<ExtraPair> pair = pick_extra_pair();
  if (!pair) return {};
  return [this, p = *pair] { align_extra_pair(p); };
}

double Pipeline::cached_overlap(const RobotRecord& target, const RobotRecord& source,
                                const Eigen::Matrix4d& T_target_source) {
  const std::pair<std::string, std::string> key{target.robot_id, source.robot_id};
  {
    std::lock_guard<std::mutex> lock(pairs_mutex_);
    const auto it = overlaps_.find(key);
    if (it != overlaps_.end() && it->second.target_hash == target.content_hash &&
        it->second.source_hash == source.content_hash) {
      if (!server::moved_noticeably(it->second.T_target_source, T_target_source, kOverlapReuseM, kOverlapReuseDeg)) {
        return it->second.overlap;
      }
    }
  }
  const double overlap = estimate_overlap(*target.map->occupied_leaves(), *source.map->occupied_leaves(), T_target_source,
                                          static_cast<std::size_t>(config_.merge.extra_overlap_samples));
  std::lock_guard<std::mutex> lock(pairs_mutex_);
  overlaps_[key] = {target.content_hash, source.content_hash, T_target_source, overlap};
  return overlap;
}

std::optional<Pipeline::ExtraPair> Pipeline::pick_extra_pair() {
  const auto poses = registry_.poses();
  std::set<std::pair<std::string, std::string>> linked;
  for (const Edge& e : registry_.edges()) linked.insert(ordered(e.target, e.source));
  std::vector<std::shared_ptr<const RobotRecord>> aligned;
  for (const auto& kv : poses) {
    if (auto r = registry_.get(kv.first); r && r->map) aligned.push_back(r);
  }
  std::optional<ExtraPair> best;
  for (std::size_t i = 0; i < aligned.size(); ++i) {
    for (std::size_t j = i + 1; j < aligned.size(); ++j) {
      const auto key = ordered(aligned[i]->robot_id, aligned[j]->robot_id);
      if (linked.count(key) != 0 || attempted(*aligned[i], *aligned[j], "extra")) continue;
      {
        std::lock_guard<std::mutex> lock(pairs_mutex_);
        if (in_progress_.count(key) != 0) continue;
      }
      // The larger map is the target; the overlap is measured on the smaller one.
      const bool i_larger = aligned[i]->map->num_nodes() >= aligned[j]->map->num_nodes();
      const RobotRecord& t = i_larger ? *aligned[i] : *aligned[j];
      const RobotRecord& s = i_larger ? *aligned[j] : *aligned[i];
      const Eigen::Matrix4d T = rigid_inverse(poses.at(t.robot_id).T_global_robot) * poses.at(s.robot_id).T_global_robot;
      const double overlap = cached_overlap(t, s, T);
      if (overlap < config_.merge.extra_min_overlap || (best && best->overlap >= overlap)) continue;
      best = ExtraPair{{t.robot_id, s.robot_id, t.map_revision, s.map_revision}, t.content_hash, s.content_hash, T, overlap};
    }
  }
  if (!best) return std::nullopt;
  std::lock_guard<std::mutex> lock(pairs_mutex_);
  if (!in_progress_.insert(ordered(best->target, best->source)).second) return std::nullopt;  // another worker took it
  return best;
}

void Pipeline::align_extra_pair(const ExtraPair& p) {
  const PairClaim claim(*this, p.target, p.source);
  const Registry::AlignmentUse hold_target(registry_, p.target), hold_source(registry_, p.source);
  auto target = prepared(p.target, false);
  auto source = prepared(p.source, false);
  if (!target || !source || stopping()) return;
  char what[64];
  std::snprintf(what, sizeof what, "extra pair, estimated overlap %.2f", p.overlap);
  spdlog::info("merge {} <- {}: {}: refining from the pose estimates", p.target, p.source, what);
  auto t0 = std::chrono::steady_clock::now();
  align::AlignResult res = align_local(*target, *source, p.T_target_source, config_.align);
  report({p.target, p.source, res.accepted, false, res.fitness, seconds_since(t0),
          std::string(what) + (res.accepted ? "" : ": " + res.reason), unix_now()});
  if (!res.accepted && config_.merge.extra_global_fallback && !stopping() &&
      (target = prepared(p.target, true)) && (source = prepared(p.source, true))) {
    t0 = std::chrono::steady_clock::now();
    res = align_global(*target, *source, config_.align, [this] { return stopping(); });
    if (stopping()) return;
    report({p.target, p.source, res.accepted, true, res.fitness, seconds_since(t0),
            std::string(what) + (res.accepted ? "" : ": " + res.reason), unix_now()});
  }
  ++extra_tried_;
  const auto records = current_records(p);
  if (!records || stopping()) return;  // a map changed meanwhile: the pair is tried again
  const auto& [t, s] = *records;
  record_attempt(*t, *s, "extra", res.accepted, res.reason);
  if (!res.accepted) return;
  if (!accept_edge(make_edge(*t, *s, res), *t, *s)) return;
  ++extra_added_;
  on_new_alignment(p.source, false);
}

std::vector<MergeReportOut> Pipeline::recent_merges() const {
  std::lock_guard<std::mutex> lock(reports_mutex_);
  return {reports_.begin(), reports_.end()};
}

}  // namespace mapmerge::server
