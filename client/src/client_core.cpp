#include "client_core.hpp"

#include <cstdlib>
#include <utility>

#include <unistd.h>

#include "mapmerge/map/map_codec.hpp"
#include "mapmerge/wire/topics.hpp"

namespace mapmerge::client::detail {
namespace {

constexpr std::size_t kMaxPoseInbox = 4096;  ///< poses queued for callbacks; oldest dropped beyond
constexpr std::size_t kMaxDeltaInbox = 8;    ///< global map deltas queued; oldest dropped beyond (the map follows)
constexpr std::chrono::milliseconds kRetryDelay{100};  ///< before writing a failed update again
constexpr std::chrono::seconds kWarningPeriod{5};       ///< at most one write-failure warning per period

TransportConfig transport_config(const Options& options) {
  TransportConfig c;
  c.domain = options.domain;
  try {
    c.profile = wire::ProfileSpec::parse(options.profile);
  } catch (const std::invalid_argument& e) {
    throw ClientError(e.what());
  }
  c.profile.discovery_server = options.discovery_server;
  c.robot_id = options.robot_id;
  c.receive_global_map = options.receive_global_map;
  c.max_block = options.max_block;
  c.security = security_options(options);
  c.participant_name = "mapmerge-client/" + (options.robot_id.empty() ? std::string("observer") : options.robot_id);
  return c;
}

Options validated(Options options) {
  if (const std::string error = check_options(options); !error.empty()) throw ClientError(error);
  if (options.frame_id.empty() && !options.robot_id.empty()) options.frame_id = options.robot_id + "/map";
  if (options.session_id.empty()) options.session_id = process_session_id();
  if (options.max_block.count() < 0) options.max_block = std::chrono::milliseconds(0);
  if (options.poll_period.count() <= 0) options.poll_period = std::chrono::milliseconds(100);
  return options;
}

template <class Callback, class... Args>
void invoke(const std::optional<Callback>& slot, Args&&... args) {
  if (slot && *slot) (*slot)(std::forward<Args>(args)...);
}

}  // namespace

ClientCore::ClientCore(Options options, Vendor vendor) : options_(validated(std::move(options))), vendor_(vendor) {
  requester_ = options_.robot_id.empty() ? "observer_" + options_.session_id + "_" + std::to_string(::getpid())
                                         : options_.robot_id;
  TransportEvents events;
  events.pose = [this](Pose&& p) { on_pose(std::move(p)); };
  events.global_map = [this](GlobalMapMessage&& m) { on_global_map(std::move(m)); };
  events.global_delta = [this](GlobalDeltaMessage&& m) { on_global_delta(std::move(m)); };
  TransportConfig config = transport_config(options_);
  if (vendor_ == Vendor::kFastdds && config.profile.discovery_server.empty()) {
    if (const char* env = std::getenv("ROS_DISCOVERY_SERVER"); env != nullptr && *env != '\0') {
      config.profile.discovery_server = env;  // as mapmerge-server and ROS 2 tools do
    }
  }
  transport_ = vendor_ == Vendor::kCyclone ? make_cyclone_transport(config, std::move(events))
                                           : make_fastdds_transport(config, std::move(events));
  dispatch_thread_ = std::thread([this] { dispatch_loop(); });
  send_thread_ = std::thread([this] { send_loop(); });
}

ClientCore::~ClientCore() {
  stop_ = true;
  {
    std::lock_guard<std::mutex> lock(inbox_mutex_);
  }
  inbox_cv_.notify_all();
  {
    std::lock_guard<std::mutex> lock(send_mutex_);
  }
  send_cv_.notify_all();
  if (dispatch_thread_.joinable()) dispatch_thread_.join();
  if (send_thread_.joinable()) send_thread_.join();
  transport_.reset();  // no DDS callback after this
}

PublishResult ClientCore::publish(const octomap::OcTree& tree) {
  PublishResult result;
  if (options_.robot_id.empty()) {
    result.error = "this client observes only (no robot id): nothing to publish";
    return result;
  }
  MapMessage message;
  try {
    message = make_map_message(tree, options_, options_.session_id, 0);
  } catch (const std::exception& e) {
    result.error = std::string("cannot serialise the map: ") + e.what();
    return result;
  }
  result.bytes = message.data.size();
  result.encoding = message.encoding;
  bool replaced = false;
  {
    // Numbered when queued, so concurrent publishers never queue a lower number after a higher one.
    std::lock_guard<std::mutex> lock(send_mutex_);
    message.sequence_number = result.sequence_number = next_sequence_++;
    replaced = outbox_.has_value() && !outbox_resend_;
    outbox_ = std::move(message);
    outbox_resend_ = false;
  }
  send_cv_.notify_all();
  if (replaced) {
    std::lock_guard<std::mutex> lock(state_mutex_);
    ++stats_.updates_coalesced;
  }
  result.queued = true;
  return result;
}

void ClientCore::send_loop() {
  std::unique_lock<std::mutex> lock(send_mutex_);
  while (!stop_) {
    send_cv_.wait(lock, [this] { return stop_ || outbox_.has_value(); });
    if (stop_) break;
    MapMessage message = std::move(*outbox_);
    outbox_.reset();
    const bool resend = std::exchange(outbox_resend_, false);
    sending_ = true;
    lock.unlock();
    const bool ok = transport_->write_map(message);
    if (!resend) {
      std::lock_guard<std::mutex> state_lock(state_mutex_);
      ++(ok ? stats_.updates_published : stats_.write_failures);
    }
    lock.lock();
    sending_ = false;
    if (ok && !resend) {
      written_ = std::move(message);
    } else if (!ok && !resend && !outbox_) {  // a failed resend is not retried: best effort
      // Not written (e.g. the writer's history stayed full for max_block): retry it unless a
      // newer update replaced it meanwhile. Failures are reported by the dispatch thread.
      outbox_ = std::move(message);
      send_cv_.wait_for(lock, kRetryDelay, [this] { return stop_.load(); });
    }
    send_cv_.notify_all();  // flush() waits for this
  }
}

bool ClientCore::flush(std::chrono::milliseconds timeout) {
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  {
    std::unique_lock<std::mutex> lock(send_mutex_);
    if (!send_cv_.wait_until(lock, deadline, [this] { return stop_ || (!outbox_ && !sending_); })) return false;
  }
  const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(deadline - std::chrono::steady_clock::now());
  return transport_->wait_for_acks(std::max(left, std::chrono::milliseconds(0)));
}

bool ClientCore::server_connected() const { return transport_->matched_servers() > 0; }

bool ClientCore::wait_for_server(std::chrono::milliseconds timeout) {
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  for (;;) {
    if (server_connected()) return true;
    if (std::chrono::steady_clock::now() >= deadline) return false;
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
}

void ClientCore::request_global_map() {
  {
    std::lock_guard<std::mutex> lock(inbox_mutex_);
    request_pending_ = true;
  }
  inbox_cv_.notify_all();
}

std::optional<Pose> ClientCore::pose(const std::string& robot_id) const {
  std::lock_guard<std::mutex> lock(state_mutex_);
  auto it = poses_.find(robot_id);
  if (it == poses_.end()) return std::nullopt;
  return it->second;
}

std::vector<Pose> ClientCore::poses() const {
  std::lock_guard<std::mutex> lock(state_mutex_);
  std::vector<Pose> out;
  for (const auto& [id, p] : poses_) out.push_back(p);
  return out;
}

std::shared_ptr<const GlobalMap> ClientCore::global_map() const {
  std::lock_guard<std::mutex> lock(state_mutex_);
  return global_map_;
}

Statistics ClientCore::statistics() const {
  std::lock_guard<std::mutex> lock(state_mutex_);
  return stats_;
}

#define MAPMERGE_SET_CALLBACK(method, slot, Type)       \
  void ClientCore::method(Type cb) {                    \
    {                                                   \
      std::lock_guard<std::mutex> lock(inbox_mutex_);   \
      pending_.slot = std::move(cb);                    \
      callbacks_pending_ = true;                        \
    }                                                   \
    inbox_cv_.notify_all();                             \
  }
MAPMERGE_SET_CALLBACK(set_own_pose_callback, own_pose, PoseCallback)
MAPMERGE_SET_CALLBACK(set_pose_callback, pose, PoseCallback)
MAPMERGE_SET_CALLBACK(set_global_map_callback, map, GlobalMapCallback)
MAPMERGE_SET_CALLBACK(set_connection_callback, connection, ConnectionCallback)
MAPMERGE_SET_CALLBACK(set_warning_callback, warning, WarningCallback)
#undef MAPMERGE_SET_CALLBACK

void ClientCore::install_callbacks(Callbacks&& pending) {
  if (pending.warning) active_.warning = std::move(pending.warning);
  const auto snapshot = poses();
  if (pending.own_pose) {
    active_.own_pose = std::move(pending.own_pose);
    if (*active_.own_pose) {
      for (const Pose& p : snapshot) {
        if (p.robot_id == options_.robot_id) (*active_.own_pose)(p);
      }
    }
  }
  if (pending.pose) {
    active_.pose = std::move(pending.pose);
    if (*active_.pose) {
      for (const Pose& p : snapshot) (*active_.pose)(p);
    }
  }
  if (pending.map) {
    active_.map = std::move(pending.map);
    const auto map = global_map();
    if (*active_.map && map) (*active_.map)(map);
  }
  if (pending.connection) {
    active_.connection = std::move(pending.connection);
    if (*active_.connection && was_connected_) (*active_.connection)(true);
  }
}

void ClientCore::on_pose(Pose&& pose) {
  {
    std::lock_guard<std::mutex> lock(inbox_mutex_);
    if (pose_inbox_.size() >= kMaxPoseInbox) pose_inbox_.pop_front();
    pose_inbox_.push_back(std::move(pose));
  }
  inbox_cv_.notify_all();
}

void ClientCore::on_global_map(GlobalMapMessage&& message) {
  {
    std::lock_guard<std::mutex> lock(inbox_mutex_);
    map_inbox_ = std::move(message);
  }
  inbox_cv_.notify_all();
}

void ClientCore::on_global_delta(GlobalDeltaMessage&& message) {
  {
    std::lock_guard<std::mutex> lock(inbox_mutex_);
    if (delta_inbox_.size() >= kMaxDeltaInbox) delta_inbox_.pop_front();
    delta_inbox_.push_back(std::move(message));
  }
  inbox_cv_.notify_all();
}

void ClientCore::warn(const std::string& message) { invoke(active_.warning, message); }

void ClientCore::check_connection() {
  const bool connected = server_connected();
  if (connected != was_connected_) {
    was_connected_ = connected;
    // A server that (re)appears gets asked for the current state (transient-local delivery to
    // late joiners is not guaranteed by every vendor), once our request writer has matched its
    // reader: requests are volatile, so one written before that match would be lost.
    ask_on_connect_ = connected;
    if (connected) resend_last_map();
    invoke(active_.connection, connected);
  }
  if (ask_on_connect_ && transport_->matched_request_readers() > 0) {
    ask_on_connect_ = false;
    if (!transport_->write_request(requester_, ++nonce_)) warn("map request could not be written");
  }
}

void ClientCore::resend_last_map() {
  // Transient-local delivery of the last map to a late-joining (or restarted) server is not
  // guaranteed by every vendor: the same update (same sequence) goes out once more; a server
  // that has it already ignores it as a duplicate.
  {
    std::lock_guard<std::mutex> lock(send_mutex_);
    if (outbox_ || sending_ || !written_) return;  // a newer update is on its way anyway
    outbox_ = *written_;
    outbox_resend_ = true;
  }
  send_cv_.notify_all();
}

void ClientCore::deliver_poses(std::deque<Pose>& poses) {
  for (Pose& p : poses) {
    {
      std::lock_guard<std::mutex> lock(state_mutex_);
      ++stats_.poses_received;
      poses_[p.robot_id] = p;
    }
    if (p.robot_id == options_.robot_id) invoke(active_.own_pose, p);
    invoke(active_.pose, p);
  }
}

void ClientCore::deliver_map(GlobalMapMessage&& message) {
  // The server republishes its map periodically (late joiners): decode and report changes only.
  // A map of the version just patched from its changed blocks hashes to what the delta said.
  const std::uint64_t hash = payload_hash(message.data);
  if (last_map_ && last_map_->first == message.version && last_map_->second == hash) return;
  last_map_ = std::make_pair(message.version, hash);
  std::string error;
  auto decoded = decode_global_map(std::move(message), options_.max_global_map_bytes, error);
  // The map it replaces is freed after the callback, outside the lock: freeing a Freiburg-size
  // octree takes longer than decoding it (~65 ms vs ~50 ms), and neither the new map's callback
  // nor a caller of global_map() should wait for that.
  std::shared_ptr<const GlobalMap> replaced;
  {
    std::lock_guard<std::mutex> lock(state_mutex_);
    ++(decoded ? stats_.global_maps_received : stats_.global_maps_rejected);
    if (decoded) replaced = std::exchange(global_map_, decoded);
  }
  if (decoded) {
    invoke(active_.map, decoded);
  } else {
    warn(error);
  }
}

void ClientCore::deliver_delta(GlobalDeltaMessage&& message) {
  // Only onto exactly the map the server made it from; any other receiver takes the full map
  // of this version, which the server sends right after.
  if (!last_map_ || last_map_->first != message.base_version || last_map_->second != message.base_hash) return;
  std::string error;
  if (message.bytes >= options_.max_global_map_bytes) {
    error = "changed blocks of " + std::to_string(message.bytes) + " bytes reach the limit of " +
            std::to_string(options_.max_global_map_bytes);
  } else {
    error = check_block_patches(message.blocks, DecodeLimits{}.max_nodes);
  }
  if (!error.empty()) {
    {
      std::lock_guard<std::mutex> lock(state_mutex_);
      ++stats_.global_deltas_rejected;
    }
    warn("global map version " + std::to_string(message.version) + ": changed blocks rejected (" + error +
         "); waiting for the whole map");
    return;
  }
  std::shared_ptr<const GlobalMap> patched;
  {
    // In place, so only while nobody else holds the map or its tree (nobody can take a new
    // reference meanwhile: global_map() needs this lock). Otherwise the whole map is decoded.
    std::lock_guard<std::mutex> lock(state_mutex_);
    if (!global_map_ || global_map_.use_count() != 1 || global_map_->tree.use_count() != 1) return;
    auto tree = std::const_pointer_cast<octomap::OcTree>(global_map_->tree);  // made mutable by decode
    apply_block_patches(*tree, message.blocks);
    auto map = std::make_shared<GlobalMap>();
    map->version = message.version;
    map->frame_id = std::move(message.frame_id);
    map->resolution = message.resolution;
    map->stamp = message.stamp;
    map->encoding = global_map_->encoding;
    map->payload_bytes = message.bytes;
    map->contributors = std::move(message.contributors);
    map->tree = std::move(tree);
    global_map_ = map;
    patched = std::move(map);
    ++stats_.global_maps_received;
    ++stats_.global_maps_patched;
  }
  last_map_ = std::make_pair(message.version, message.hash);
  invoke(active_.map, patched);
}

void ClientCore::report_write_failures() {
  std::uint64_t failures = 0;
  {
    std::lock_guard<std::mutex> lock(state_mutex_);
    failures = stats_.write_failures;
  }
  const auto now = std::chrono::steady_clock::now();
  if (failures <= failures_reported_ || (failures_reported_ > 0 && now - last_failure_warning_ < kWarningPeriod)) {
    return;
  }
  failures_reported_ = failures;
  last_failure_warning_ = now;
  warn("map update could not be written (" + std::to_string(failures) + " failures so far)");
}

void ClientCore::dispatch_loop() {
  while (!stop_) {
    std::deque<Pose> poses;
    std::optional<GlobalMapMessage> map;
    std::deque<GlobalDeltaMessage> deltas;
    Callbacks callbacks;
    bool request = false, install = false;
    {
      std::unique_lock<std::mutex> lock(inbox_mutex_);
      inbox_cv_.wait_for(lock, options_.poll_period, [this] {
        return stop_ || !pose_inbox_.empty() || map_inbox_ || !delta_inbox_.empty() || request_pending_ ||
               callbacks_pending_;
      });
      if (stop_) break;
      poses.swap(pose_inbox_);
      map.swap(map_inbox_);
      deltas.swap(delta_inbox_);
      request = std::exchange(request_pending_, false);
      install = std::exchange(callbacks_pending_, false);
      if (install) callbacks = std::exchange(pending_, Callbacks{});
    }
    if (install) install_callbacks(std::move(callbacks));
    check_connection();
    if (request && !transport_->write_request(requester_, ++nonce_)) warn("map request could not be written");
    deliver_poses(poses);
    for (GlobalDeltaMessage& d : deltas) deliver_delta(std::move(d));  // before the map they make needless
    if (map) deliver_map(std::move(*map));
    report_write_failures();
  }
}

}  // namespace mapmerge::client::detail
