#include "mapmerge/server/dds_io.hpp"

#include <algorithm>
#include <atomic>
#include <map>
#include <mutex>
#include <set>

#include <fastdds/dds/domain/DomainParticipantListener.hpp>
#include <fastdds/dds/subscriber/SampleInfo.hpp>
#include <spdlog/spdlog.h>

#include "dds_convert.hpp"
#include "mapmerge/wire/fastdds.hpp"
#include "mapmerge/wire/topics.hpp"
#include "mapmerge_fastdds/mapmergePubSubTypes.h"
#include "mapmerge_fastdds/ros2_msgsPubSubTypes.h"

namespace mapmerge::server {
namespace fdds = eprosima::fastdds::dds;
using OctomapMsg = octomap_msgs::msg::dds_::Octomap_;
using ReturnCode_t = eprosima::fastrtps::types::ReturnCode_t;

namespace {

/// A robot map topic seen in discovery.
struct RobotTopic {
  std::string name;
  std::string robot;
  bool ros = false;
};

/// Hears every remote writer; keeps those on robot map topics for the main loop to subscribe.
class DiscoveryListener : public fdds::DomainParticipantListener {
 public:
  DiscoveryListener(std::string ros_pattern, std::function<void()> notify)
      : ros_pattern_(std::move(ros_pattern)), notify_(std::move(notify)) {}

  void on_publisher_discovery(fdds::DomainParticipant*, eprosima::fastrtps::rtps::WriterDiscoveryInfo&& info) override {
    if (info.status != eprosima::fastrtps::rtps::WriterDiscoveryInfo::DISCOVERED_WRITER) return;
    const std::string topic = info.info.topicName().to_string();
    const std::string type = info.info.typeName().to_string();
    RobotTopic t{topic, "", false};
    if (auto r = wire::robot_of_map_topic(topic); r && type == mapmerge::MapUpdatePubSubType().getName()) {
      t.robot = *r;
    } else if (auto r2 = wire::robot_of_ros_octomap_topic(topic, ros_pattern_);
               r2 && type == OctomapMsg_PubSubType_name() && topic != wire::kRosGlobalMapTopic) {
      t.robot = *r2;
      t.ros = true;
    } else {
      return;
    }
    if (!wire::is_valid_robot_id(t.robot)) return;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      if (!seen_.insert(topic).second) return;
      pending_.push_back(t);
    }
    if (notify_) notify_();
  }

  std::vector<RobotTopic> take() {
    std::lock_guard<std::mutex> lock(mutex_);
    return std::exchange(pending_, {});
  }

 private:
  static std::string OctomapMsg_PubSubType_name() { return octomap_msgs::msg::dds_::Octomap_PubSubType().getName(); }
  std::string ros_pattern_;
  std::function<void()> notify_;
  std::mutex mutex_;
  std::set<std::string> seen_;
  std::vector<RobotTopic> pending_;
};

/// Counts the matched map writers of each robot (over all its topics) and reports when a robot
/// gets its first one or loses its last one.
class Presence {
 public:
  explicit Presence(std::function<void(const std::string&, bool)> report) : report_(std::move(report)) {}
  void change(const std::string& robot, int delta) {
    bool alive = false;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      int& n = writers_[robot];
      const int before = n;
      n = std::max(0, n + delta);
      if ((before > 0) == (n > 0)) return;
      alive = n > 0;
    }
    if (report_) report_(robot, alive);
  }

 private:
  std::function<void(const std::string&, bool)> report_;
  std::mutex mutex_;
  std::map<std::string, int> writers_;
};

/// Reads one robot topic and hands every valid sample on; tells `presence` of its writers.
template <class Msg>
class MapReaderListener : public fdds::DataReaderListener {
 public:
  MapReaderListener(RobotTopic topic, std::function<void(MapSample)> sink, Presence& presence)
      : topic_(std::move(topic)), sink_(std::move(sink)), presence_(presence) {}

  /// A writer matched or went: it left, or its participant's lease expired (any vendor).
  void on_subscription_matched(fdds::DataReader*, const fdds::SubscriptionMatchedStatus& info) override {
    presence_.change(topic_.robot, info.current_count_change);
  }

  void on_data_available(fdds::DataReader* reader) override {
    Msg msg;
    fdds::SampleInfo info;
    while (reader->take_next_sample(&msg, &info) == ReturnCode_t::RETCODE_OK) {
      if (!info.valid_data) continue;
      sink_(convert_sample(msg));
    }
  }

 private:
  MapSample convert_sample(const mapmerge::MapUpdate& m) { return convert::from_native(m, topic_.name, topic_.robot); }
  /// ROS 2 maps carry no sequence number: the server numbers them on arrival (Server::on_map).
  MapSample convert_sample(const OctomapMsg& m) { return convert::from_ros(m, topic_.name, topic_.robot, 0); }

  RobotTopic topic_;
  std::function<void(MapSample)> sink_;
  Presence& presence_;
};

class RequestListener : public fdds::DataReaderListener {
 public:
  explicit RequestListener(std::function<void(const std::string&)> sink) : sink_(std::move(sink)) {}
  void on_data_available(fdds::DataReader* reader) override {
    mapmerge::MapRequest msg;
    fdds::SampleInfo info;
    while (reader->take_next_sample(&msg, &info) == ReturnCode_t::RETCODE_OK) {
      if (info.valid_data && sink_) sink_(msg.requester());
    }
  }

 private:
  std::function<void(const std::string&)> sink_;
};

/// The explicit keystore, else ROS 2's ROS_SECURITY_* environment, else off.
wire::SecurityOptions security_options(const NetworkConfig& config) {
  if (config.security_keystore.empty()) return wire::SecurityOptions::from_environment(config.security_enclave);
  return wire::SecurityOptions{config.security_keystore, config.security_enclave};
}

}  // namespace

struct DdsIo::Impl {
  Callbacks callbacks;
  Presence presence;
  DiscoveryListener discovery;
  std::unique_ptr<wire::FastddsParticipant> participant;  // after the listeners it references
  RequestListener request_listener;
  std::vector<std::unique_ptr<fdds::DataReaderListener>> reader_listeners;
  fdds::DataWriter* global_writer = nullptr;
  fdds::DataWriter* delta_writer = nullptr;  ///< null when DDS refused it (e.g. an older keystore)
  fdds::DataWriter* ros_global_writer = nullptr;
  fdds::DataWriter* pose_writer = nullptr;
  fdds::DataWriter* tf_writer = nullptr;
  fdds::DataWriter* status_writer = nullptr;
  std::mutex write_mutex;

  Impl(const NetworkConfig& config, Callbacks cb)
      : callbacks(std::move(cb)),
        presence(callbacks.on_presence),
        discovery(config.ros_octomap_pattern, callbacks.on_discovery),
        request_listener(callbacks.on_request) {}

  /// Creates a reader for `t`; false (logged) when DDS refuses it, e.g. a topic outside the
  /// server's permissions: one bad topic never stops the server.
  bool subscribe(const RobotTopic& t) {
    try {
      create_reader(t);
      return true;
    } catch (const wire::DdsError& e) {
      spdlog::warn("robot topic {}: no reader ({}); skipped", t.name, e.what());
      return false;
    }
  }

  void create_reader(const RobotTopic& t) {
    auto& p = *participant;
    if (t.ros) {
      auto l = std::make_unique<MapReaderListener<OctomapMsg>>(t, callbacks.on_map, presence);
      p.create_reader(p.topic<octomap_msgs::msg::dds_::Octomap_PubSubType>(t.name), wire::TopicKind::State, l.get());
      reader_listeners.push_back(std::move(l));
    } else {
      auto l = std::make_unique<MapReaderListener<mapmerge::MapUpdate>>(t, callbacks.on_map, presence);
      p.create_reader(p.topic<mapmerge::MapUpdatePubSubType>(t.name), wire::TopicKind::State, l.get());
      reader_listeners.push_back(std::move(l));
    }
  }
};

DdsIo::DdsIo(const NetworkConfig& config, Callbacks callbacks)
    : impl_(std::make_unique<Impl>(config, std::move(callbacks))) {
  wire::ParticipantOptions options;
  options.domain = config.domain;
  options.profile = wire::ProfileSpec::parse(config.profile);
  options.profile.discovery_server = config.discovery_server;
  options.name = "mapmerge-server";
  options.discover_all_topics = true;  // robots' map topics appear in discovery before we read them
  options.security = security_options(config);
  spdlog::info("DDS security: {}", options.security.describe());
  impl_->participant = std::make_unique<wire::FastddsParticipant>(options, &impl_->discovery,
                                                                  fdds::StatusMask::none());
  auto& p = *impl_->participant;
  using wire::TopicKind;
  impl_->global_writer = p.create_writer(p.topic<mapmerge::GlobalMapPubSubType>(wire::kGlobalMapTopic), TopicKind::State);
  impl_->ros_global_writer = p.create_writer(
      p.topic<octomap_msgs::msg::dds_::Octomap_PubSubType>(wire::kRosGlobalMapTopic), TopicKind::State);
  try {  // receivers fall back to the full map without it: a keystore from before it must not stop us
    impl_->delta_writer =
        p.create_writer(p.topic<mapmerge::GlobalMapDeltaPubSubType>(wire::kGlobalDeltaTopic), TopicKind::Event);
  } catch (const wire::DdsError& e) {
    spdlog::warn("{}: no writer ({}); global maps are sent whole only", wire::kGlobalDeltaTopic, e.what());
  }
  impl_->pose_writer = p.create_writer(p.topic<mapmerge::RobotPosePubSubType>(wire::kPosesTopic), TopicKind::State);
  impl_->tf_writer = p.create_writer(p.topic<tf2_msgs::msg::dds_::TFMessage_PubSubType>(wire::kTfTopic), TopicKind::Event);
  impl_->status_writer = p.create_writer(p.topic<mapmerge::ServerStatusPubSubType>(wire::kStatusTopic), TopicKind::Event);
  p.create_reader(p.topic<mapmerge::MapRequestPubSubType>(wire::kRequestTopic), TopicKind::Event, &impl_->request_listener);
}

DdsIo::~DdsIo() {
  // Entities go first (no callback may run into a destroyed listener), then the listeners.
  impl_->participant.reset();
}

std::vector<std::string> DdsIo::service() {
  std::vector<std::string> names;
  for (const RobotTopic& t : impl_->discovery.take()) {
    if (impl_->subscribe(t)) names.push_back(t.name);
  }
  return names;
}

void DdsIo::publish_global(const GlobalMapOut& global) {
  std::lock_guard<std::mutex> lock(impl_->write_mutex);
  auto native = convert::to_native(global);
  auto ros = convert::to_ros(global);
  impl_->global_writer->write(&native);
  impl_->ros_global_writer->write(&ros);
}

void DdsIo::publish_delta(const GlobalMapOut& global) {
  if (!global.delta || impl_->delta_writer == nullptr) return;
  std::lock_guard<std::mutex> lock(impl_->write_mutex);
  auto delta = convert::to_native_delta(global);
  impl_->delta_writer->write(&delta);
}

void DdsIo::publish_poses(const std::vector<PoseOut>& poses, std::uint64_t version, const std::string& global_frame) {
  std::lock_guard<std::mutex> lock(impl_->write_mutex);
  tf2_msgs::msg::dds_::TFMessage_ tf;
  for (const PoseOut& p : poses) {
    auto native = convert::to_native(p, version, global_frame);
    impl_->pose_writer->write(&native);
    if (p.state == PoseState::kAligned) tf.transforms().push_back(convert::to_tf(p, global_frame));
  }
  if (!tf.transforms().empty()) impl_->tf_writer->write(&tf);
}

void DdsIo::publish_status(const StatusOut& status) {
  std::lock_guard<std::mutex> lock(impl_->write_mutex);
  auto native = convert::to_native(status);
  impl_->status_writer->write(&native);
}

}  // namespace mapmerge::server
