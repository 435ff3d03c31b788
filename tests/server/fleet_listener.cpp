#include "fleet.hpp"

#include <algorithm>
#include <set>

#include <fastdds/dds/subscriber/SampleInfo.hpp>

#include "mapmerge/map/map_codec.hpp"
#include "mapmerge/wire/topics.hpp"
#include "mapmerge_fastdds/mapmergePubSubTypes.h"
#include "mapmerge_fastdds/ros2_msgsPubSubTypes.h"

namespace mapmerge::test {
namespace fdds = eprosima::fastdds::dds;
using ReturnCode_t = eprosima::fastrtps::types::ReturnCode_t;

struct FleetListener::Impl {
  mutable std::mutex mutex;
  std::condition_variable cv;
  std::map<std::string, ReceivedPose> poses;
  ReceivedGlobal global;
  std::size_t globals = 0;
  std::uint64_t ros_bytes = 0;
  std::vector<std::string> tf_children;
  std::vector<ReceivedMerge> merges;
  std::set<std::string> merge_keys;
  ReceivedStatus status;
  Acknowledged acked;
  GlobalObserver observer;
  bool decode_globals = true;

  void acknowledge(const std::string& robot, const std::string& session, std::uint64_t sequence) {
    std::uint64_t& seq = acked.sequence[robot + "/" + session];
    seq = std::max(seq, sequence);
  }

  void on_status(const mapmerge::ServerStatus& s) {
    for (const auto& m : s.recent_merges()) {
      const std::string key = m.target_robot() + "<" + m.source_robot() + "@" + std::to_string(m.stamp().sec()) + "." +
                              std::to_string(m.stamp().nanosec());
      if (merge_keys.insert(key).second) {
        merges.push_back({m.target_robot(), m.source_robot(), m.accepted(), m.global_search(), m.detail()});
      }
    }
    status.updates_received = s.updates_received();
    status.updates_rejected = s.updates_rejected();
    status.updates_ignored = s.updates_ignored();
    status.merges_run = s.merges_run();
    status.merges_coalesced = s.merges_coalesced();
    status.global_version = s.global_version();
    for (const auto& r : s.robots()) {
      status.accepted[r.robot_id()] = r.updates_accepted();
      status.sequence[r.robot_id()] = r.sequence_number();
      status.rejected[r.robot_id()] = r.updates_rejected();
      status.ignored[r.robot_id()] = r.updates_ignored();
      status.resolution[r.robot_id()] = r.resolution();
      status.last_error[r.robot_id()] = r.last_error();
      status.session[r.robot_id()] = r.session_id();
      status.alive[r.robot_id()] = r.alive();
      status.times_lost[r.robot_id()] = r.times_lost();
      if (r.sequence_number() > 0) acknowledge(r.robot_id(), r.session_id(), r.sequence_number());
    }
    status.store_ok = s.store_ok();
    status.store_error = s.store_error();
    status.store_failures = s.store_failures();
    status.store_pending = s.store_pending();
    status.merges_queued = s.merges_queued();
    status.merges_queued_max = s.merges_queued_max();
    status.merges_running = s.merges_running();
    ++status.count;
  }

  /// Calls `f` for every sample, under the mutex unless `kLocked` is false (`f` then locks).
  template <class Msg, class F, bool kLocked = true>
  struct Reader : fdds::DataReaderListener {
    Impl* impl;
    F f;
    Reader(Impl* i, F fn) : impl(i), f(std::move(fn)) {}
    void on_data_available(fdds::DataReader* r) override {
      Msg m;
      fdds::SampleInfo info;
      while (r->take_next_sample(&m, &info) == ReturnCode_t::RETCODE_OK) {
        if (!info.valid_data) continue;
        if (kLocked) {
          std::lock_guard<std::mutex> lock(impl->mutex);
          f(m);
        } else {
          f(m);
        }
        impl->cv.notify_all();
      }
    }
  };
  std::vector<std::unique_ptr<fdds::DataReaderListener>> listeners;
  std::unique_ptr<wire::FastddsParticipant> participant;
  fdds::DataWriter* request_writer = nullptr;

  template <class PubSub, class Msg, bool kLocked = true, class F>
  void subscribe(const char* topic, wire::TopicKind kind, F f) {
    auto l = std::make_unique<Reader<Msg, F, kLocked>>(this, std::move(f));
    participant->create_reader(participant->topic<PubSub>(topic), kind, l.get());
    listeners.push_back(std::move(l));
  }

  void on_pose(const mapmerge::RobotPose& p) {
    ReceivedPose r;
    const auto& t = p.T_global_robot().translation();
    const auto& q = p.T_global_robot().rotation();
    r.T_global_robot.topLeftCorner<3, 3>() = Eigen::Quaterniond(q[3], q[0], q[1], q[2]).toRotationMatrix();
    r.T_global_robot.topRightCorner<3, 1>() = Eigen::Vector3d(t[0], t[1], t[2]);
    r.status = static_cast<int>(p.status());
    r.global_version = p.global_version();
    r.fitness = p.fitness();
    poses[p.robot_id()] = r;
    if (r.status == 1) acked.aligned_pose[p.robot_id()] = r.T_global_robot;
  }

  /// Decodes outside the mutex, and frees the map it replaces after the new one is taken: a
  /// Freiburg-size global map takes ~50 ms to decode and ~65 ms to free.
  void on_global(const mapmerge::GlobalMap& g) {
    const auto arrived = std::chrono::steady_clock::now();
    bool decode = false;
    {
      std::lock_guard<std::mutex> lock(mutex);
      decode = decode_globals;
    }
    std::shared_ptr<octomap::OcTree> tree;
    if (decode) {
      auto decoded = decode_map(g.data(), g.encoding(), DecodeLimits{});
      if (!decoded.ok()) return;
      tree = std::shared_ptr<octomap::OcTree>(std::move(decoded.tree));
    }
    std::shared_ptr<octomap::OcTree> replaced;
    std::lock_guard<std::mutex> lock(mutex);
    if (g.version() < acked.global_version) ++acked.version_regressions;
    acked.global_version = std::max(acked.global_version, g.version());
    for (const auto& c : g.contributors()) acknowledge(c.robot_id(), c.session_id(), c.sequence_number());
    global.version = g.version();
    replaced = std::move(global.tree);
    global.tree = std::move(tree);
    global.contributors.clear();
    global.contributor_sequence.clear();
    for (const auto& c : g.contributors()) {
      global.contributors.push_back(c.robot_id());
      global.contributor_sequence[c.robot_id()] = c.sequence_number();
    }
    if (observer) observer(global.version, global.contributor_sequence);
    global.received = std::chrono::steady_clock::now();
    global.arrived = arrived;
    ++globals;
    cv.notify_all();  // before `replaced` is freed
  }
};

FleetListener::FleetListener(int domain, const wire::ProfileSpec& profile, const wire::SecurityOptions& security)
    : impl_(std::make_unique<Impl>()) {
  wire::ParticipantOptions o;
  o.domain = domain;
  o.profile = profile;
  o.security = security;
  o.name = "fleet_listener";
  impl_->participant = std::make_unique<wire::FastddsParticipant>(o);
  Impl* impl = impl_.get();
  using wire::TopicKind;
  impl->subscribe<mapmerge::RobotPosePubSubType, mapmerge::RobotPose>(
      wire::kPosesTopic, TopicKind::State, [impl](const mapmerge::RobotPose& p) { impl->on_pose(p); });
  impl->subscribe<mapmerge::GlobalMapPubSubType, mapmerge::GlobalMap, false>(
      wire::kGlobalMapTopic, TopicKind::State, [impl](const mapmerge::GlobalMap& g) { impl->on_global(g); });
  impl->subscribe<octomap_msgs::msg::dds_::Octomap_PubSubType, octomap_msgs::msg::dds_::Octomap_>(
      wire::kRosGlobalMapTopic, TopicKind::State,
      [impl](const octomap_msgs::msg::dds_::Octomap_& m) { impl->ros_bytes = m.data().size(); });
  impl->subscribe<tf2_msgs::msg::dds_::TFMessage_PubSubType, tf2_msgs::msg::dds_::TFMessage_>(
      wire::kTfTopic, TopicKind::Event, [impl](const tf2_msgs::msg::dds_::TFMessage_& m) {
        for (const auto& t : m.transforms()) {
          if (std::find(impl->tf_children.begin(), impl->tf_children.end(), t.child_frame_id()) == impl->tf_children.end())
            impl->tf_children.push_back(t.child_frame_id());
        }
      });
  impl->subscribe<mapmerge::ServerStatusPubSubType, mapmerge::ServerStatus>(
      wire::kStatusTopic, TopicKind::Event, [impl](const mapmerge::ServerStatus& s) { impl->on_status(s); });
  impl->request_writer = impl->participant->create_writer(
      impl->participant->topic<mapmerge::MapRequestPubSubType>(wire::kRequestTopic), TopicKind::Event);
}

FleetListener::~FleetListener() { impl_->participant.reset(); }

bool FleetListener::wait_for(const std::function<bool()>& pred, std::chrono::seconds timeout) {
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  while (std::chrono::steady_clock::now() < deadline) {
    if (pred()) return true;
    std::unique_lock<std::mutex> lock(impl_->mutex);
    impl_->cv.wait_for(lock, std::chrono::milliseconds(100));
  }
  return pred();
}

void FleetListener::request() {
  mapmerge::MapRequest r;
  r.requester("fleet_listener");
  r.nonce(1);
  impl_->request_writer->write(&r);
}

std::map<std::string, ReceivedPose> FleetListener::poses() const {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  return impl_->poses;
}
ReceivedGlobal FleetListener::global() const {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  return impl_->global;
}
std::uint64_t FleetListener::ros_global_bytes() const {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  return impl_->ros_bytes;
}
std::vector<std::string> FleetListener::tf_children() const {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  return impl_->tf_children;
}
std::size_t FleetListener::globals_received() const {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  return impl_->globals;
}

std::vector<ReceivedMerge> FleetListener::merges() const {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  return impl_->merges;
}
ReceivedStatus FleetListener::status() const {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  return impl_->status;
}
void FleetListener::observe_globals(GlobalObserver observer, bool decode) {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  impl_->observer = std::move(observer);
  impl_->decode_globals = decode;
}

Acknowledged FleetListener::acknowledged() const {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  return impl_->acked;
}

}  // namespace mapmerge::test
