#include "mapmerge/server/server.hpp"

#include <malloc.h>

#include <utility>

#include <spdlog/spdlog.h>

#include "mapmerge/server/global_map.hpp"

namespace mapmerge::server {
namespace {

constexpr auto kLoopPeriod = std::chrono::milliseconds(50);  ///< main loop wake-up when idle

std::chrono::duration<double> seconds(double s) { return std::chrono::duration<double>(s); }

}  // namespace

Server::Server(ServerConfig config) : config_(std::move(config)) {
  if (!config_.store.state_dir.empty()) store_ = std::make_unique<Store>(config_.store);
  if (!config_.merge.reference.empty()) registry_.claim_reference(config_.merge.reference);
  registry_.set_conflict_hold(config_.merge.session_conflict_hold_s);
  Pipeline::Hooks hooks;
  hooks.retry = [this](const std::string& robot) { scheduler_->retry(robot); };
  hooks.changed = [this] {
    dirty_ = true;
    cv_.notify_all();
  };
  hooks.cancelled = [this] { return stopping_.load(); };
  hooks.refine = [this](const std::string& job) { scheduler_->background(job); };
  hooks.search = [this](const std::string& job) { scheduler_->background(job); };
  hooks.more_idle_work = [this] {
    if (scheduler_) scheduler_->kick_idle();
  };
  pipeline_ = std::make_unique<Pipeline>(config_, registry_, store_.get(), hooks);
  restore();
  scheduler_ = std::make_unique<Scheduler>(
      config_.merge.ingest_threads,
      [this](const std::string& robot, std::optional<MapSample> map, bool retry) {
        pipeline_->process(robot, std::move(map), retry);
      },
      [this] { return pipeline_->next_idle_work(); }, config_.merge.extra_max_jobs,
      Scheduler::Lanes{config_.merge.threads, config_.merge.merge_nice});
  DdsIo::Callbacks callbacks;
  callbacks.on_map = [this](MapSample s) { on_map(std::move(s)); };
  callbacks.on_request = [this](const std::string& who) {
    spdlog::info("map request from {}: republishing", who);
    requested_ = true;
    cv_.notify_all();
  };
  callbacks.on_discovery = [this] { cv_.notify_all(); };
  callbacks.on_presence = [this](const std::string& robot, bool alive) { on_presence(robot, alive); };
  dds_ = std::make_unique<DdsIo>(config_.network, callbacks);
  spdlog::info("serving on domain {} with profile {}{}", config_.network.domain, config_.network.profile,
               config_.network.discovery_server.empty() ? "" : " via discovery server " + config_.network.discovery_server);
  if (last_global_) republish();
  for (const auto& rec : registry_.all()) {
    if (registry_.status(rec->robot_id) != RobotStatus::kAligned) scheduler_->retry(rec->robot_id);
  }
  scheduler_->kick_idle();  // extra pairs not tried before the restart
}

Server::~Server() {
  stop();
  dds_.reset();        // no more callbacks
  scheduler_.reset();  // joins the workers
}

void Server::restore() {
  if (!store_) return;
  StoreSnapshot snap = store_->load();
  if (!snap.reference.empty()) registry_.claim_reference(snap.reference);
  for (const MapSample& m : snap.maps) {
    registry_.admit(m.robot_id, m.session_id, m.sequence);
    pipeline_->restore(m);
  }
  for (const Edge& e : snap.edges) registry_.put_edge(e);
  pipeline_->restore_attempts(snap.attempts);
  if (snap.global) {
    version_ = snap.global->version;
    last_global_ = std::move(snap.global);
  }
  for (const MapSample& m : snap.maps) {
    spdlog::info("robot {} restored: map {}/{} ({})", m.topic_robot, m.session_id, m.sequence,
                 to_string(registry_.status(m.topic_robot)));
  }
  if (!global_is_current()) {
    // Maps stored after the last global map (a crash before it was built): build it again now,
    // robots republishing the same maps would be ignored as duplicates.
    dirty_ = true;
  }
  spdlog::info("restored {} robots, {} alignments ({} rejected by the pose graph), {} pairs tried, global map "
               "version {} from {}", snap.maps.size(), snap.edges.size(), registry_.rejected_edges().size(),
               snap.attempts.size(), version_, store_->path());
}

bool Server::global_is_current() const {
  const auto poses = registry_.poses();
  if (!last_global_) return poses.empty();
  std::size_t matched = 0;
  for (const Contribution& c : last_global_->contributors) {
    const auto rec = registry_.get(c.robot_id);
    if (!rec || poses.count(c.robot_id) == 0 || rec->session_id != c.session_id || rec->sequence != c.sequence) {
      return false;
    }
    ++matched;
  }
  return matched == poses.size();
}

void Server::on_presence(const std::string& robot, bool alive) {
  if (!registry_.set_alive(robot, alive)) return;
  if (alive) {
    spdlog::info("robot {} present: a writer of its map topic matched", robot);
  } else {
    spdlog::warn("robot {} lost: no writer of its map topic left (it left, or its lease expired); its map {}", robot,
                 config_.merge.keep_lost_maps ? "stays in the global map" : "is left out of the global map");
  }
  if (!config_.merge.keep_lost_maps && registry_.get(robot)) {
    dirty_ = true;  // the global map changes: the robot leaves it, or comes back
    cv_.notify_all();
  }
}

void Server::on_map(MapSample sample) {
  ++received_;
  // ROS 2 maps carry no sequence number: each is the next after what the registry holds, also
  // after a restart restored a higher number than this reader counted.
  if (sample.ros) sample.sequence = registry_.next_sequence(sample.topic_robot, sample.session_id);
  const std::string& robot = sample.topic_robot;
  const Admission a = registry_.admit(robot, sample.session_id, sample.sequence);
  if (a == Admission::kDuplicate || a == Admission::kOutOfOrder) {
    ++ignored_;
    if (a == Admission::kDuplicate) {
      spdlog::debug("robot {}: update {}/{} ignored (held already)", robot, sample.session_id, sample.sequence);
    } else {
      spdlog::info("robot {}: update {}/{} ignored: older than the update held", robot, sample.session_id,
                   sample.sequence);
    }
    return;
  }
  if (a == Admission::kConflict) {
    ++conflicting_;
    const std::string in_force = registry_.session_of(robot);
    const std::string reason = "robot id " + robot + " is used by two participants: session " + sample.session_id +
                               " was replaced by session " + in_force + ", which still publishes; updates of " +
                               sample.session_id + " are ignored (give each robot its own id)";
    registry_.reject(robot, reason);
    if (registry_.first_conflict(robot, sample.session_id)) spdlog::warn("robot {}: {}", robot, reason);
    return;
  }
  if (a == Admission::kNewSession) spdlog::info("robot {}: new session {}", robot, sample.session_id);
  scheduler_->submit(std::move(sample));
}

void Server::run() {
  while (!stopping_) {
    {
      std::unique_lock<std::mutex> lock(mutex_);
      cv_.wait_for(lock, kLoopPeriod);
    }
    if (stopping_) break;
    loop_once();
  }
  spdlog::info("shutting down");
  scheduler_->stop();
  const auto c = pipeline_->counters();
  spdlog::info("pose graph: {} edges, {} rejected; extra pairs: {} tried, {} edges added; rescues: {} tried, {} accepted",
               registry_.edges().size(), registry_.rejected_edges().size(), c.extra_pairs_tried, c.extra_edges_added,
               c.rescues_tried, c.rescues_accepted);
}

void Server::stop() {
  stopping_ = true;
  cv_.notify_all();
}

void Server::loop_once() {
  for (const std::string& topic : dds_->service()) spdlog::info("robot topic {} discovered: subscribed", topic);
  const auto now = Clock::now();
  if (dirty_ && now - last_build_ >= seconds(config_.publish.min_interval_s)) {
    dirty_ = false;
    last_build_ = now;
    publish_global();
  } else if (requested_.exchange(false) || now - last_republish_ >= seconds(config_.publish.republish_period_s)) {
    republish();
  }
  if (store_ && now - last_store_retry_ >= seconds(config_.store.retry_period_s)) {
    last_store_retry_ = now;
    store_->retry();  // writes that failed (disk full, read-only): logged and on the status topic
  }
  if (now - last_status_ >= seconds(config_.publish.status_period_s)) {
    publish_status();
    if (store_) store_->checkpoint();  // here, not after a commit on the update path
    if (pipeline_->alignment_data_idle()) scheduler_->background(Pipeline::release_job());
    scheduler_->kick_idle();  // rescues fall due as refusals age (merge.idle_rescue_after_s)
    if (std::exchange(trim_due_, false)) {
      // Replaced maps were freed since: give their pages back (RSS of fr_079 x2 at 1 Hz 417 ->
      // 220 MB; ~5 ms, on this loop after the publication, not on the update path).
      const auto t0 = Clock::now();
      malloc_trim(0);
      spdlog::debug("heap trimmed in {:.1f} ms", std::chrono::duration<double>(Clock::now() - t0).count() * 1e3);
    }
  }
}

void Server::publish_global() {
  const auto t0 = Clock::now();
  auto global = builder_.build(registry_, version_ + 1);
  if (!global) {
    builder_.release_replaced();
    if (builder_.unchanged()) {  // poses moved, the map did not: no new version
      spdlog::debug("global map {} unchanged: poses published", version_);
      dds_->publish_poses(current_poses(), version_, config_.merge.global_frame);
    }
    if (builder_.deferred()) dirty_ = true;  // robots still to fuse whole
    return;
  }
  const auto t_built = Clock::now();
  version_ = global->version;
  const auto poses = current_poses();
  if (store_ && !store_->save_global(*global, poses)) {
    spdlog::error("global map {} served from memory only until the store works again", version_);
  }
  const auto t_stored = Clock::now();
  last_global_ = std::move(global);
  dds_->publish_delta(*last_global_);
  const std::size_t delta_blocks = last_global_->delta ? last_global_->delta->blocks.size() : 0;
  const bool delta = last_global_->delta.has_value();
  last_global_->delta.reset();  // sent once; republications send the map
  republish();
  const auto t_published = Clock::now();
  builder_.release_replaced();
  trim_due_ = true;
  std::string unaligned;
  for (const PoseOut& p : poses) {
    if (p.state != PoseState::kAligned) unaligned += " " + p.robot_id;
  }
  if (builder_.deferred()) {  // robots to fuse whole next: build again (after min_interval_s)
    dirty_ = true;
    cv_.notify_all();
  }
  const auto st = builder_.last_stages();
  auto ms = [](Clock::duration d) { return std::chrono::duration<double, std::milli>(d).count(); };
  spdlog::info("global map {} published: {} robots ({} re-fused, {} by difference, {} of them on the payload bytes), "
               "{} bytes{}{} in {:.0f} ms (fuse {:.0f}: diff {:.0f}, place {:.0f} for {} cubes; encode {:.0f}, poses {:.0f}, "
               "store {:.0f}, publish {:.0f}); poses of {} robots{}{}",
               version_, last_global_->contributors.size(), st.updated, st.incremental, st.from_bodies,
               last_global_->data.size(),
               delta ? fmt::format(" (and {} changed blocks)", delta_blocks) : std::string(),
               st.moving > 0 ? fmt::format(", {} robots moving in steps", st.moving) : std::string(),
               ms(t_published - t0), st.fuse_s * 1e3, st.diff_s * 1e3, st.place_s * 1e3, st.cubes, st.encode_s * 1e3,
               ms(t_built - t0) - (st.fuse_s + st.encode_s) * 1e3, ms(t_stored - t_built), ms(t_published - t_stored),
               poses.size(), unaligned.empty() ? "" : ", not aligned:", unaligned);
}

void Server::republish() {
  last_republish_ = Clock::now();
  if (last_global_) dds_->publish_global(*last_global_);
  dds_->publish_poses(current_poses(), version_, config_.merge.global_frame);
}

std::vector<PoseOut> Server::current_poses() const { return pose_outputs(registry_); }

void Server::publish_status() {
  last_status_ = Clock::now();
  StatusOut s;
  s.global_version = version_;
  for (const auto& rec : registry_.all()) {
    const RobotStatus st = registry_.status(rec->robot_id);
    const PoseState ps = st == RobotStatus::kAligned ? PoseState::kAligned
                         : st == RobotStatus::kRejected ? PoseState::kRejected : PoseState::kUnknown;
    const Registry::Presence presence = registry_.presence(rec->robot_id);
    s.robots.push_back({rec->robot_id, ps, rec->session_id, rec->sequence, rec->resolution, rec->updates_accepted,
                        rec->updates_rejected, registry_.ignored(rec->robot_id), rec->last_error, presence.alive,
                        presence.times_lost});
  }
  if (store_) {
    const StoreHealth h = store_->health();
    s.store_ok = h.ok;
    s.store_error = h.error;
    s.store_failures = h.failures;
    s.store_pending = h.pending;
  }
  s.recent_merges = pipeline_->recent_merges();
  for (const auto& e : registry_.rejected_edges()) {  // left out of the fleet pose graph
    MergeReportOut r;
    r.target = e.target;
    r.source = e.source;
    r.accepted = false;
    r.global_search = false;
    r.detail = "rejected by the pose graph: " + e.reason + (e.evidence.empty() ? "" : "; evidence: " + e.evidence);
    r.stamp_unix = unix_now();
    s.recent_merges.push_back(r);
  }
  const auto c = pipeline_->counters();
  const auto sched = scheduler_->stats();
  s.updates_received = received_;
  s.updates_rejected = c.updates_rejected + conflicting_;
  s.updates_ignored = ignored_;
  s.merges_run = c.merges_run;
  s.merges_coalesced = sched.coalesced;
  s.merges_queued = sched.queued;
  s.merges_queued_max = sched.max_queued;
  s.merges_running = sched.running;
  dds_->publish_status(s);
}

}  // namespace mapmerge::server
