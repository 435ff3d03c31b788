// The Fast DDS transport of a client: a map writer, a request writer, pose and global-map
// readers, on the topics of mapmerge::wire with the QoS of idl/profiles/fastdds_qos.xml.

#include <atomic>
#include <utility>

#include <fastdds/dds/log/Log.hpp>
#include <fastdds/dds/log/StdoutErrConsumer.hpp>
#include <fastdds/dds/subscriber/DataReaderListener.hpp>
#include <fastdds/dds/subscriber/SampleInfo.hpp>

#include "mapmerge/wire/fastdds.hpp"
#include "mapmerge/wire/topics.hpp"
#include "mapmerge_fastdds/mapmergePubSubTypes.h"
#include "transport.hpp"

namespace mapmerge::client::detail {
namespace {

namespace fdds = eprosima::fastdds::dds;
using eprosima::fastrtps::types::ReturnCode_t;

eprosima::fastrtps::Duration_t to_duration(std::chrono::milliseconds ms) {
  const auto count = std::max<std::int64_t>(0, ms.count());
  return eprosima::fastrtps::Duration_t(static_cast<std::int32_t>(count / 1000),
                                        static_cast<std::uint32_t>((count % 1000) * 1000000));
}

PoseStatus to_status(mapmerge::PoseStatus status) {
  switch (status) {
    case mapmerge::POSE_ALIGNED: return PoseStatus::kAligned;
    case mapmerge::POSE_REJECTED: return PoseStatus::kRejected;
    default: return PoseStatus::kUnknown;
  }
}

/// Bounds how long a write may block the thread calling it (reliable history full).
void limit_blocking(fdds::DataWriter* writer, std::chrono::milliseconds max_block) {
  fdds::DataWriterQos qos = writer->get_qos();
  qos.reliability().max_blocking_time = to_duration(max_block);
  if (writer->set_qos(qos) != ReturnCode_t::RETCODE_OK) {
    throw wire::DdsError("cannot set the max blocking time of writer on " + writer->get_topic()->get_name());
  }
}

Pose to_pose(const mapmerge::RobotPose& s) {
  Pose p;
  p.robot_id = s.robot_id();
  p.status = to_status(s.status());
  p.translation = s.T_global_robot().translation();
  p.rotation = s.T_global_robot().rotation();
  p.fitness = s.fitness();
  p.quality = s.quality();
  p.global_version = s.global_version();
  p.global_frame_id = s.global_frame_id();
  p.robot_frame_id = s.robot_frame_id();
  p.stamp = to_seconds(s.stamp().sec(), s.stamp().nanosec());
  return p;
}

GlobalMapMessage to_message(mapmerge::GlobalMap&& s) {
  GlobalMapMessage m;
  m.version = s.version();
  m.stamp = to_seconds(s.stamp().sec(), s.stamp().nanosec());
  m.frame_id = s.frame_id();
  m.resolution = s.resolution();
  m.encoding = s.encoding();
  m.data = std::move(s.data());
  for (const auto& c : s.contributors()) m.contributors.push_back({c.robot_id(), c.session_id(), c.sequence_number()});
  return m;
}

GlobalDeltaMessage to_message(mapmerge::GlobalMapDelta&& s) {
  GlobalDeltaMessage m;
  m.version = s.version();
  m.base_version = s.base_version();
  m.base_hash = s.base_hash();
  m.hash = s.hash();
  m.stamp = to_seconds(s.stamp().sec(), s.stamp().nanosec());
  m.frame_id = s.frame_id();
  m.resolution = s.resolution();
  m.blocks.reserve(s.blocks().size());
  for (auto& b : s.blocks()) {
    m.bytes += b.records().size();
    m.blocks.push_back(BlockPatch{b.block(), static_cast<BlockState>(b.state()), std::move(b.records())});
  }
  for (const auto& c : s.contributors()) m.contributors.push_back({c.robot_id(), c.session_id(), c.sequence_number()});
  return m;
}

/// Takes every sample of type Sample from a reader and hands each valid one to `sink`.
template <class Sample>
class TakeAllListener : public fdds::DataReaderListener {
 public:
  explicit TakeAllListener(std::function<void(Sample&&)> sink) : sink_(std::move(sink)) {}
  void stop() { stopped_ = true; }
  void on_data_available(fdds::DataReader* reader) override {
    Sample sample;
    fdds::SampleInfo info;
    while (!stopped_ && reader->take_next_sample(&sample, &info) == ReturnCode_t::RETCODE_OK) {
      if (info.valid_data) sink_(std::move(sample));
      sample = Sample();
    }
  }

 private:
  std::function<void(Sample&&)> sink_;
  std::atomic<bool> stopped_{false};
};

class FastddsTransport final : public Transport {
 public:
  FastddsTransport(const TransportConfig& config, TransportEvents events)
      : events_(std::move(events)),
        pose_listener_([this](mapmerge::RobotPose&& s) { events_.pose(to_pose(s)); }),
        map_listener_([this](mapmerge::GlobalMap&& s) { events_.global_map(to_message(std::move(s))); }),
        delta_listener_([this](mapmerge::GlobalMapDelta&& s) { events_.global_delta(to_message(std::move(s))); }) {
    wire::ParticipantOptions options;
    options.domain = config.domain;
    options.profile = config.profile;
    options.name = config.participant_name;
    options.security = config.security;
    participant_ = std::make_unique<wire::FastddsParticipant>(options);
    auto& p = *participant_;
    if (!config.robot_id.empty()) {
      map_writer_ = p.create_writer(p.topic<mapmerge::MapUpdatePubSubType>(wire::map_topic(config.robot_id)),
                                    wire::TopicKind::State);
      limit_blocking(map_writer_, config.max_block);
    }
    request_writer_ = p.create_writer(p.topic<mapmerge::MapRequestPubSubType>(wire::kRequestTopic),
                                      wire::TopicKind::Event);
    limit_blocking(request_writer_, config.max_block);
    pose_reader_ = p.create_reader(p.topic<mapmerge::RobotPosePubSubType>(wire::kPosesTopic),
                                   wire::TopicKind::State, &pose_listener_);
    if (config.receive_global_map) {
      map_reader_ = p.create_reader(p.topic<mapmerge::GlobalMapPubSubType>(wire::kGlobalMapTopic),
                                    wire::TopicKind::State, &map_listener_);
      try {  // without it (e.g. a keystore from before the topic) every version is decoded whole
        delta_reader_ = p.create_reader(p.topic<mapmerge::GlobalMapDeltaPubSubType>(wire::kGlobalDeltaTopic),
                                        wire::TopicKind::Event, &delta_listener_);
      } catch (const wire::DdsError&) {
        delta_reader_ = nullptr;
      }
    }
  }

  ~FastddsTransport() override {
    pose_listener_.stop();
    map_listener_.stop();
    delta_listener_.stop();
    if (pose_reader_ != nullptr) pose_reader_->set_listener(nullptr);
    if (map_reader_ != nullptr) map_reader_->set_listener(nullptr);
    if (delta_reader_ != nullptr) delta_reader_->set_listener(nullptr);
    participant_.reset();  // deletes every entity before the listeners go
  }

  bool write_map(const MapMessage& m) override {
    if (map_writer_ == nullptr) return false;
    mapmerge::MapUpdate s;
    s.robot_id(m.robot_id);
    s.session_id(m.session_id);
    s.sequence_number(m.sequence_number);
    s.stamp().sec(m.stamp_sec);
    s.stamp().nanosec(m.stamp_nanosec);
    s.frame_id(m.frame_id);
    s.resolution(m.resolution);
    s.encoding(m.encoding);
    s.data(m.data);
    return map_writer_->write(&s);
  }

  bool write_request(const std::string& requester, std::uint64_t nonce) override {
    mapmerge::MapRequest s;
    s.requester(requester);
    s.nonce(nonce);
    return request_writer_->write(&s);
  }

  int matched_request_readers() const override {
    fdds::PublicationMatchedStatus status;
    if (request_writer_->get_publication_matched_status(status) != ReturnCode_t::RETCODE_OK) return 0;
    return status.current_count;
  }

  int matched_servers() const override {
    int n = 0;
    fdds::SubscriptionMatchedStatus status;
    if (pose_reader_->get_subscription_matched_status(status) == ReturnCode_t::RETCODE_OK) {
      n = std::max(n, status.current_count);
    }
    if (map_reader_ != nullptr &&
        map_reader_->get_subscription_matched_status(status) == ReturnCode_t::RETCODE_OK) {
      n = std::max(n, status.current_count);
    }
    return n;
  }

  bool wait_for_acks(std::chrono::milliseconds timeout) override {
    if (map_writer_ == nullptr) return true;
    return map_writer_->wait_for_acknowledgments(to_duration(timeout)) == ReturnCode_t::RETCODE_OK;
  }

 private:
  TransportEvents events_;
  TakeAllListener<mapmerge::RobotPose> pose_listener_;
  TakeAllListener<mapmerge::GlobalMap> map_listener_;
  TakeAllListener<mapmerge::GlobalMapDelta> delta_listener_;
  std::unique_ptr<wire::FastddsParticipant> participant_;  // after the listeners: deleted first
  fdds::DataWriter* map_writer_ = nullptr;
  fdds::DataWriter* request_writer_ = nullptr;
  fdds::DataReader* pose_reader_ = nullptr;
  fdds::DataReader* map_reader_ = nullptr;
  fdds::DataReader* delta_reader_ = nullptr;
};

}  // namespace

std::unique_ptr<Transport> make_fastdds_transport(const TransportConfig& config, TransportEvents events) {
  try {
    return std::make_unique<FastddsTransport>(config, std::move(events));
  } catch (const std::exception& e) {  // wire::DdsError, or std::invalid_argument from security
    throw ClientError(std::string("Fast DDS: ") + e.what());
  }
}

}  // namespace mapmerge::client::detail

namespace mapmerge::client {

void route_dds_logs_to_stderr() {
  using eprosima::fastdds::dds::Log;
  Log::ClearConsumers();
  Log::RegisterConsumer(std::make_unique<eprosima::fastdds::dds::StdoutErrConsumer>());
}

}  // namespace mapmerge::client
