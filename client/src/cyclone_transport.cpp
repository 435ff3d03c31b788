// The Cyclone DDS (C API) transport of a client: the same topics, types and QoS as the Fast DDS
// one. A reader thread waits on a waitset and takes the samples.

#include <atomic>
#include <thread>
#include <utility>

#include "mapmerge/wire/cyclone.hpp"
#include "mapmerge/wire/topics.hpp"
#include "mapmerge_cyclone/mapmerge.h"
#include "transport.hpp"

namespace mapmerge::client::detail {
namespace {

constexpr int kTakeBatch = 8;  ///< samples taken per dds_take call
constexpr dds_duration_t kWaitsetPeriod = DDS_MSECS(100);  ///< reader thread's wake-up period

PoseStatus to_status(mapmerge_PoseStatus status) {
  switch (status) {
    case mapmerge_POSE_ALIGNED: return PoseStatus::kAligned;
    case mapmerge_POSE_REJECTED: return PoseStatus::kRejected;
    default: return PoseStatus::kUnknown;
  }
}

std::string str(const char* s) { return s == nullptr ? std::string() : std::string(s); }

Pose to_pose(const mapmerge_RobotPose& s) {
  Pose p;
  p.robot_id = str(s.robot_id);
  p.status = to_status(s.status);
  for (int i = 0; i < 3; ++i) p.translation[i] = s.T_global_robot.translation[i];
  for (int i = 0; i < 4; ++i) p.rotation[i] = s.T_global_robot.rotation[i];
  p.fitness = s.fitness;
  p.quality = s.quality;
  p.global_version = s.global_version;
  p.global_frame_id = str(s.global_frame_id);
  p.robot_frame_id = str(s.robot_frame_id);
  p.stamp = to_seconds(s.stamp.sec, s.stamp.nanosec);
  return p;
}

GlobalMapMessage to_message(const mapmerge_GlobalMap& s) {
  GlobalMapMessage m;
  m.version = s.version;
  m.stamp = to_seconds(s.stamp.sec, s.stamp.nanosec);
  m.frame_id = str(s.frame_id);
  m.resolution = s.resolution;
  m.encoding = str(s.encoding);
  if (s.data._buffer != nullptr) m.data.assign(s.data._buffer, s.data._buffer + s.data._length);
  for (uint32_t i = 0; i < s.contributors._length; ++i) {
    const auto& c = s.contributors._buffer[i];
    m.contributors.push_back({str(c.robot_id), str(c.session_id), c.sequence_number});
  }
  return m;
}

GlobalDeltaMessage to_message(const mapmerge_GlobalMapDelta& s) {
  GlobalDeltaMessage m;
  m.version = s.version;
  m.base_version = s.base_version;
  m.base_hash = s.base_hash;
  m.hash = s.hash;
  m.stamp = to_seconds(s.stamp.sec, s.stamp.nanosec);
  m.frame_id = str(s.frame_id);
  m.resolution = s.resolution;
  m.blocks.reserve(s.blocks._length);
  for (uint32_t i = 0; i < s.blocks._length; ++i) {
    const auto& b = s.blocks._buffer[i];
    BlockPatch p{b.block, static_cast<BlockState>(b.state), {}};
    if (b.records._buffer != nullptr) p.records.assign(b.records._buffer, b.records._buffer + b.records._length);
    m.bytes += p.records.size();
    m.blocks.push_back(std::move(p));
  }
  for (uint32_t i = 0; i < s.contributors._length; ++i) {
    const auto& c = s.contributors._buffer[i];
    m.contributors.push_back({str(c.robot_id), str(c.session_id), c.sequence_number});
  }
  return m;
}

/// Takes every available sample of `reader` (loaned) and hands each valid one to `sink`.
template <class Sample, class Sink>
void take_all(dds_entity_t reader, Sink&& sink) {
  for (;;) {
    void* samples[kTakeBatch] = {};
    dds_sample_info_t infos[kTakeBatch];
    const dds_return_t n = dds_take(reader, samples, infos, kTakeBatch, kTakeBatch);
    if (n <= 0) return;
    for (dds_return_t i = 0; i < n; ++i) {
      if (infos[i].valid_data) sink(*static_cast<const Sample*>(samples[i]));
    }
    dds_return_loan(reader, samples, n);
  }
}

int matched_writers(dds_entity_t reader) {
  if (reader <= 0) return 0;
  dds_subscription_matched_status_t status{};
  if (dds_get_subscription_matched_status(reader, &status) < 0) return 0;
  return static_cast<int>(status.current_count);
}

class CycloneTransport final : public Transport {
 public:
  CycloneTransport(const TransportConfig& config, TransportEvents events)
      : events_(std::move(events)), participant_(config.domain, config.profile, config.security) {
    auto& p = participant_;
    if (!config.robot_id.empty()) {
      map_writer_ = create_writer(p.topic(&mapmerge_MapUpdate_desc, wire::map_topic(config.robot_id)),
                                  wire::TopicKind::State, config.max_block);
    }
    request_writer_ = create_writer(p.topic(&mapmerge_MapRequest_desc, wire::kRequestTopic), wire::TopicKind::Event,
                                    config.max_block);
    pose_reader_ = p.create_reader(p.topic(&mapmerge_RobotPose_desc, wire::kPosesTopic), wire::TopicKind::State);
    if (config.receive_global_map) {
      map_reader_ = p.create_reader(p.topic(&mapmerge_GlobalMap_desc, wire::kGlobalMapTopic), wire::TopicKind::State);
      try {  // without it (e.g. a keystore from before the topic) every version is decoded whole
        delta_reader_ = p.create_reader(p.topic(&mapmerge_GlobalMapDelta_desc, wire::kGlobalDeltaTopic),
                                        wire::TopicKind::Event);
      } catch (const wire::CycloneError&) {
        delta_reader_ = 0;
      }
    }
    waitset_ = dds_create_waitset(p.participant());
    wakeup_ = dds_create_guardcondition(p.participant());
    if (waitset_ < 0 || wakeup_ < 0) throw wire::CycloneError("cannot create Cyclone waitset");
    attach(pose_reader_);
    attach(map_reader_);
    attach(delta_reader_);
    dds_waitset_attach(waitset_, wakeup_, 0);
    thread_ = std::thread([this] { run(); });
  }

  ~CycloneTransport() override {
    stop_ = true;
    dds_set_guardcondition(wakeup_, true);
    if (thread_.joinable()) thread_.join();
    // participant_'s destructor deletes every entity.
  }

  bool write_map(const MapMessage& m) override {
    if (map_writer_ <= 0) return false;
    mapmerge_MapUpdate s{};
    s.robot_id = const_cast<char*>(m.robot_id.c_str());
    s.session_id = const_cast<char*>(m.session_id.c_str());
    s.sequence_number = m.sequence_number;
    s.stamp.sec = m.stamp_sec;
    s.stamp.nanosec = m.stamp_nanosec;
    s.frame_id = const_cast<char*>(m.frame_id.c_str());
    s.resolution = m.resolution;
    s.encoding = const_cast<char*>(m.encoding.c_str());
    s.data._buffer = const_cast<uint8_t*>(m.data.data());
    s.data._length = static_cast<uint32_t>(m.data.size());
    s.data._maximum = s.data._length;
    s.data._release = false;
    return dds_write(map_writer_, &s) >= 0;
  }

  bool write_request(const std::string& requester, std::uint64_t nonce) override {
    mapmerge_MapRequest s{};
    s.requester = const_cast<char*>(requester.c_str());
    s.nonce = nonce;
    return dds_write(request_writer_, &s) >= 0;
  }

  int matched_servers() const override {
    return std::max(matched_writers(pose_reader_), matched_writers(map_reader_));
  }

  int matched_request_readers() const override {
    dds_publication_matched_status_t status{};
    if (request_writer_ <= 0 || dds_get_publication_matched_status(request_writer_, &status) < 0) return 0;
    return static_cast<int>(status.current_count);
  }

  bool wait_for_acks(std::chrono::milliseconds timeout) override {
    if (map_writer_ <= 0) return true;
    return dds_wait_for_acks(map_writer_, DDS_MSECS(timeout.count())) == DDS_RETCODE_OK;
  }

 private:
  /// A writer of the topic kind's QoS whose writes block at most `max_block`.
  dds_entity_t create_writer(dds_entity_t topic, wire::TopicKind kind, std::chrono::milliseconds max_block) {
    dds_qos_t* qos = wire::make_cyclone_qos(kind);
    dds_qset_reliability(qos, DDS_RELIABILITY_RELIABLE, DDS_MSECS(max_block.count()));
    const dds_entity_t w = dds_create_writer(participant_.participant(), topic, qos, nullptr);
    dds_delete_qos(qos);
    if (w < 0) throw wire::CycloneError(std::string("cannot create Cyclone writer: ") + dds_strretcode(w));
    return w;
  }

  void attach(dds_entity_t reader) {
    if (reader <= 0) return;
    const dds_entity_t condition = dds_create_readcondition(reader, DDS_ANY_STATE);
    if (condition < 0) throw wire::CycloneError("cannot create Cyclone read condition");
    dds_waitset_attach(waitset_, condition, reader);
  }

  void run() {
    while (!stop_) {
      dds_waitset_wait(waitset_, nullptr, 0, kWaitsetPeriod);
      if (stop_) break;
      take_all<mapmerge_RobotPose>(pose_reader_, [this](const mapmerge_RobotPose& s) { events_.pose(to_pose(s)); });
      if (delta_reader_ > 0) {  // before the map: a delta makes decoding the map of its version needless
        take_all<mapmerge_GlobalMapDelta>(
            delta_reader_, [this](const mapmerge_GlobalMapDelta& s) { events_.global_delta(to_message(s)); });
      }
      if (map_reader_ > 0) {
        take_all<mapmerge_GlobalMap>(map_reader_,
                                     [this](const mapmerge_GlobalMap& s) { events_.global_map(to_message(s)); });
      }
    }
  }

  TransportEvents events_;
  wire::CycloneParticipant participant_;
  dds_entity_t map_writer_ = 0;
  dds_entity_t request_writer_ = 0;
  dds_entity_t pose_reader_ = 0;
  dds_entity_t map_reader_ = 0;
  dds_entity_t delta_reader_ = 0;
  dds_entity_t waitset_ = 0;
  dds_entity_t wakeup_ = 0;
  std::atomic<bool> stop_{false};
  std::thread thread_;
};

}  // namespace

std::unique_ptr<Transport> make_cyclone_transport(const TransportConfig& config, TransportEvents events) {
  if (!config.profile.discovery_server.empty()) {
    throw ClientError("Cyclone DDS: a Fast DDS discovery server is not supported (use --vendor fastdds)");
  }
  try {
    return std::make_unique<CycloneTransport>(config, std::move(events));
  } catch (const std::exception& e) {  // wire::CycloneError, or std::invalid_argument from security
    throw ClientError(std::string("Cyclone DDS: ") + e.what());
  }
}

}  // namespace mapmerge::client::detail
