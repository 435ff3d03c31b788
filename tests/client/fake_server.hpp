#pragma once
/// A stand-in for mapmerge-server, built on the wire library's Fast DDS participant: it reads
/// robots' map updates and map requests and publishes poses and global maps, so the client
/// library can be tested without the real server.

#include <chrono>
#include <memory>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include <fastdds/dds/subscriber/SampleInfo.hpp>
#include <gtest/gtest.h>

#include "mapmerge/wire/fastdds.hpp"
#include "mapmerge/wire/topics.hpp"
#include "mapmerge_fastdds/mapmergePubSubTypes.h"

namespace mapmerge::test {

class FakeServer {
 public:
  /// `discovery_server`: "HOST:PORT" of a Fast DDS discovery server; empty: simple discovery.
  /// `security`: the server's DDS Security identity; default: off.
  explicit FakeServer(int domain, const std::string& discovery_server = "", wire::SecurityOptions security = {}) {
    wire::ParticipantOptions o;
    o.domain = domain;
    o.profile.discovery_server = discovery_server;
    o.security = std::move(security);
    o.name = "fake-mapmerge-server";
    participant_ = std::make_unique<wire::FastddsParticipant>(o);
    auto& p = *participant_;
    pose_writer_ = p.create_writer(p.topic<mapmerge::RobotPosePubSubType>(wire::kPosesTopic), wire::TopicKind::State);
    map_writer_ = p.create_writer(p.topic<mapmerge::GlobalMapPubSubType>(wire::kGlobalMapTopic), wire::TopicKind::State);
    request_reader_ = p.create_reader(p.topic<mapmerge::MapRequestPubSubType>(wire::kRequestTopic), wire::TopicKind::Event);
  }

  /// Starts reading a robot's map topic.
  void listen_to(const std::string& robot) {
    auto& p = *participant_;
    map_readers_.push_back(MapListener{
        robot, p.create_reader(p.topic<mapmerge::MapUpdatePubSubType>(wire::map_topic(robot)), wire::TopicKind::State),
        std::nullopt});
  }

  /// The next new map update of `robot`, waiting up to `timeout`. A client may send its last
  /// update once more (same session and sequence, e.g. when it notices a server appear); like
  /// the real server, a repeat of the update taken last is skipped, and must be byte-identical.
  std::optional<mapmerge::MapUpdate> take_map(const std::string& robot, std::chrono::milliseconds timeout) {
    for (auto& listener : map_readers_) {
      if (listener.robot != robot) continue;
      const auto deadline = std::chrono::steady_clock::now() + timeout;
      while (std::chrono::steady_clock::now() < deadline) {
        mapmerge::MapUpdate sample;
        eprosima::fastdds::dds::SampleInfo info;
        if (listener.reader->take_next_sample(&sample, &info) == ReturnCode_t::RETCODE_OK && info.valid_data) {
          if (listener.last && sample.session_id() == listener.last->session_id() &&
              sample.sequence_number() == listener.last->sequence_number()) {
            if (sample.data() != listener.last->data()) {
              ADD_FAILURE() << robot << ": update " << sample.sequence_number() << " repeated with other bytes";
            }
            continue;
          }
          listener.last = sample;
          return sample;
        }
        listener.reader->wait_for_unread_message(eprosima::fastrtps::Duration_t(0, 50000000));
      }
    }
    return std::nullopt;
  }

  /// The next map request, waiting up to `timeout`.
  std::optional<mapmerge::MapRequest> take_request(std::chrono::milliseconds timeout) {
    const auto deadline = std::chrono::steady_clock::now() + timeout;
    while (std::chrono::steady_clock::now() < deadline) {
      mapmerge::MapRequest sample;
      eprosima::fastdds::dds::SampleInfo info;
      if (request_reader_->take_next_sample(&sample, &info) == ReturnCode_t::RETCODE_OK && info.valid_data) {
        return sample;
      }
      request_reader_->wait_for_unread_message(eprosima::fastrtps::Duration_t(0, 50000000));
    }
    return std::nullopt;
  }

  static mapmerge::RobotPose make_pose(const std::string& robot, mapmerge::PoseStatus status,
                                       std::array<double, 3> t, std::array<double, 4> q, std::uint64_t version) {
    mapmerge::RobotPose pose;
    pose.robot_id(robot);
    pose.global_frame_id("global");
    pose.robot_frame_id(robot + "/map");
    pose.T_global_robot().translation(t);
    pose.T_global_robot().rotation(q);
    pose.fitness(0.02);
    pose.quality(0.9);
    pose.status(status);
    pose.global_version(version);
    return pose;
  }

  bool publish_pose(mapmerge::RobotPose pose) { return pose_writer_->write(&pose); }

  bool publish_global(std::vector<std::uint8_t> bytes, const std::string& encoding, std::uint64_t version,
                      const std::vector<std::string>& robots) {
    mapmerge::GlobalMap map;
    map.version(version);
    map.frame_id("global");
    map.resolution(0.05);
    map.encoding(encoding);
    map.data(std::move(bytes));
    for (const auto& r : robots) {
      mapmerge::MapContribution c;
      c.robot_id(r);
      c.session_id("s");
      c.sequence_number(1);
      map.contributors().push_back(c);
    }
    return map_writer_->write(&map);
  }

 private:
  using ReturnCode_t = eprosima::fastrtps::types::ReturnCode_t;
  std::unique_ptr<wire::FastddsParticipant> participant_;
  eprosima::fastdds::dds::DataWriter* pose_writer_ = nullptr;
  eprosima::fastdds::dds::DataWriter* map_writer_ = nullptr;
  eprosima::fastdds::dds::DataReader* request_reader_ = nullptr;
  struct MapListener {
    std::string robot;
    eprosima::fastdds::dds::DataReader* reader = nullptr;
    std::optional<mapmerge::MapUpdate> last;  ///< the update take_map() returned last
  };
  std::vector<MapListener> map_readers_;
};

}  // namespace mapmerge::test
