// The wire works both ways across vendors: a Fast DDS writer and a Cyclone DDS reader (and the
// reverse) exchange a real OctoMap, byte for byte, as a native map update and as a ROS 2
// octomap_msgs/Octomap, over the `local` (loopback-only) profile.

#include <chrono>
#include <fstream>
#include <iterator>
#include <thread>
#include <vector>

#include <gtest/gtest.h>

#include "dds_test_env.hpp"
#include "mapmerge/wire/cyclone.hpp"
#include "mapmerge/wire/fastdds.hpp"
#include "mapmerge/wire/topics.hpp"
#include "mapmerge_cyclone/mapmerge.h"
#include "mapmerge_cyclone/ros2_msgs.h"
#include "mapmerge_fastdds/mapmergePubSubTypes.h"
#include "mapmerge_fastdds/ros2_msgsPubSubTypes.h"

#include <fastrtps/attributes/LibrarySettingsAttributes.h>
#include <fastrtps/xmlparser/XMLProfileManager.h>

namespace mapmerge::wire {
namespace {

namespace fdds = eprosima::fastdds::dds;
using namespace std::chrono_literals;

constexpr auto kDeliveryTimeout = 30s;

std::vector<uint8_t> read_bytes(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  EXPECT_TRUE(in) << path;
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

std::vector<uint8_t> sample_map() { return read_bytes(std::string(MAPMERGE_DATA_DIR) + "/fr_079.bt"); }

/// Takes one sample from a Cyclone reader, waiting up to kDeliveryTimeout.
template <class Sample, class Copy>
bool cyclone_take_one(dds_entity_t reader, Copy&& copy) {
  const auto deadline = std::chrono::steady_clock::now() + kDeliveryTimeout;
  while (std::chrono::steady_clock::now() < deadline) {
    void* samples[1] = {nullptr};
    dds_sample_info_t info;
    const dds_return_t n = dds_take(reader, samples, &info, 1, 1);
    if (n > 0 && info.valid_data) {
      copy(*static_cast<const Sample*>(samples[0]));
      dds_return_loan(reader, samples, n);
      return true;
    }
    if (n > 0) dds_return_loan(reader, samples, n);
    std::this_thread::sleep_for(10ms);
  }
  return false;
}

/// Takes one sample from a Fast DDS reader, waiting up to kDeliveryTimeout.
template <class Sample>
bool fastdds_take_one(fdds::DataReader* reader, Sample& out) {
  const auto deadline = std::chrono::steady_clock::now() + kDeliveryTimeout;
  while (std::chrono::steady_clock::now() < deadline) {
    fdds::SampleInfo info;
    if (reader->take_next_sample(&out, &info) == ReturnCode_t::RETCODE_OK && info.valid_data) return true;
    reader->wait_for_unread_message(eprosima::fastrtps::Duration_t(0, 100000000));
  }
  return false;
}

class WireRoundTrip : public ::testing::Test {
 protected:
  ParticipantOptions options() const {
    ParticipantOptions o;
    o.domain = test::dds_domain();
    o.name = "wire_roundtrip";
    return o;
  }
};

TEST_F(WireRoundTrip, MapUpdateFromFastddsToCyclone) {
  const auto bytes = sample_map();
  ASSERT_GT(bytes.size(), 100000u);
  FastddsParticipant fast(options());
  auto* writer = fast.create_writer(fast.topic<mapmerge::MapUpdatePubSubType>(map_topic("r1")), TopicKind::State);
  mapmerge::MapUpdate update;
  update.robot_id("r1");
  update.session_id("s-1");
  update.sequence_number(7);
  update.frame_id("r1/map");
  update.resolution(0.05);
  update.encoding("octomap-bt");
  update.data(bytes);
  ASSERT_TRUE(writer->write(&update));  // before the reader exists: transient-local delivers it

  CycloneParticipant cyclone(options().domain, ProfileSpec{});
  const dds_entity_t reader =
      cyclone.create_reader(cyclone.topic(&mapmerge_MapUpdate_desc, map_topic("r1")), TopicKind::State);
  std::vector<uint8_t> received;
  std::string robot, encoding;
  uint64_t sequence = 0;
  ASSERT_TRUE(cyclone_take_one<mapmerge_MapUpdate>(reader, [&](const mapmerge_MapUpdate& s) {
    received.assign(s.data._buffer, s.data._buffer + s.data._length);
    robot = s.robot_id;
    encoding = s.encoding;
    sequence = s.sequence_number;
  })) << "no map update reached the Cyclone reader";
  EXPECT_EQ(robot, "r1");
  EXPECT_EQ(encoding, "octomap-bt");
  EXPECT_EQ(sequence, 7u);
  EXPECT_EQ(received, bytes);
}

TEST_F(WireRoundTrip, MapUpdateFromCycloneToFastdds) {
  auto bytes = sample_map();
  CycloneParticipant cyclone(options().domain, ProfileSpec{});
  const dds_entity_t writer =
      cyclone.create_writer(cyclone.topic(&mapmerge_MapUpdate_desc, map_topic("r2")), TopicKind::State);
  mapmerge_MapUpdate update{};
  update.robot_id = const_cast<char*>("r2");
  update.session_id = const_cast<char*>("s-2");
  update.sequence_number = 3;
  update.frame_id = const_cast<char*>("r2/map");
  update.resolution = 0.05;
  update.encoding = const_cast<char*>("octomap-bt");
  update.data._buffer = bytes.data();
  update.data._length = static_cast<uint32_t>(bytes.size());
  update.data._maximum = update.data._length;
  update.data._release = false;
  ASSERT_GE(dds_write(writer, &update), 0);

  FastddsParticipant fast(options());
  auto* reader = fast.create_reader(fast.topic<mapmerge::MapUpdatePubSubType>(map_topic("r2")), TopicKind::State);
  mapmerge::MapUpdate received;
  ASSERT_TRUE(fastdds_take_one(reader, received)) << "no map update reached the Fast DDS reader";
  EXPECT_EQ(received.robot_id(), "r2");
  EXPECT_EQ(received.sequence_number(), 3u);
  EXPECT_EQ(received.data(), bytes);
}

TEST_F(WireRoundTrip, TwoFastddsParticipantsOfOneProcessDiscoverThroughTheTransportAndExchangeData) {
  // Discovery delivered in-process can deadlock Fast DDS 2.9 when a process holding several
  // participants deletes a writer while a remote participant's lease runs out (idl/wire/src/
  // fastdds.cpp): the library keeps discovery on the transport, user data in-process.
  const auto bytes = sample_map();
  FastddsParticipant a(options());
  EXPECT_EQ(eprosima::fastrtps::xmlparser::XMLProfileManager::library_settings().intraprocess_delivery,
            eprosima::fastrtps::INTRAPROCESS_USER_DATA_ONLY);
  auto* writer = a.create_writer(a.topic<mapmerge::MapUpdatePubSubType>(map_topic("r3")), TopicKind::State);
  mapmerge::MapUpdate update;
  update.robot_id("r3");
  update.sequence_number(5);
  update.encoding("octomap-bt");
  update.data(bytes);
  ASSERT_TRUE(writer->write(&update));
  {
    FastddsParticipant b(options());
    auto* reader = b.create_reader(b.topic<mapmerge::MapUpdatePubSubType>(map_topic("r3")), TopicKind::State);
    mapmerge::MapUpdate received;
    ASSERT_TRUE(fastdds_take_one(reader, received)) << "no map update reached the other participant";
    EXPECT_EQ(received.sequence_number(), 5u);
    EXPECT_EQ(received.data(), bytes);
  }
  // The reader's participant is gone; the writer's deletes its writer after it (the order of the
  // hang seen).
}

TEST_F(WireRoundTrip, RosOctomapFromFastddsToCyclone) {
  const auto bytes = sample_map();
  FastddsParticipant fast(options());
  auto* writer = fast.create_writer(
      fast.topic<octomap_msgs::msg::dds_::Octomap_PubSubType>(ros_octomap_topic("r3")), TopicKind::State);
  octomap_msgs::msg::dds_::Octomap_ msg;
  msg.header().frame_id("r3/map");
  msg.header().stamp().sec(12);
  msg.binary(true);
  msg.id("OcTree");
  msg.resolution(0.05);
  msg.data(std::vector<int8_t>(bytes.begin(), bytes.end()));
  ASSERT_TRUE(writer->write(&msg));

  CycloneParticipant cyclone(options().domain, ProfileSpec{});
  const dds_entity_t reader = cyclone.create_reader(
      cyclone.topic(&octomap_msgs_msg_dds__Octomap__desc, ros_octomap_topic("r3")), TopicKind::State);
  std::vector<uint8_t> received;
  std::string id, frame;
  int32_t sec = 0;
  ASSERT_TRUE(cyclone_take_one<octomap_msgs_msg_dds__Octomap_>(reader, [&](const octomap_msgs_msg_dds__Octomap_& s) {
    const auto* p = reinterpret_cast<const uint8_t*>(s.data._buffer);
    received.assign(p, p + s.data._length);
    id = s.id;
    frame = s.header.frame_id;
    sec = s.header.stamp.sec;
  })) << "no octomap_msgs/Octomap reached the Cyclone reader";
  EXPECT_EQ(id, "OcTree");
  EXPECT_EQ(frame, "r3/map");
  EXPECT_EQ(sec, 12);
  EXPECT_EQ(received, bytes);
}

TEST_F(WireRoundTrip, RosOctomapFromCycloneToFastdds) {
  auto bytes = sample_map();
  CycloneParticipant cyclone(options().domain, ProfileSpec{});
  const dds_entity_t writer = cyclone.create_writer(
      cyclone.topic(&octomap_msgs_msg_dds__Octomap__desc, ros_octomap_topic("r4")), TopicKind::State);
  octomap_msgs_msg_dds__Octomap_ msg{};
  msg.header.frame_id = const_cast<char*>("r4/map");
  msg.binary = true;
  msg.id = const_cast<char*>("OcTree");
  msg.resolution = 0.05;
  msg.data._buffer = reinterpret_cast<int8_t*>(bytes.data());
  msg.data._length = static_cast<uint32_t>(bytes.size());
  msg.data._maximum = msg.data._length;
  msg.data._release = false;
  ASSERT_GE(dds_write(writer, &msg), 0);

  FastddsParticipant fast(options());
  auto* reader = fast.create_reader(
      fast.topic<octomap_msgs::msg::dds_::Octomap_PubSubType>(ros_octomap_topic("r4")), TopicKind::State);
  octomap_msgs::msg::dds_::Octomap_ received;
  ASSERT_TRUE(fastdds_take_one(reader, received)) << "no octomap_msgs/Octomap reached the Fast DDS reader";
  EXPECT_EQ(received.id(), "OcTree");
  EXPECT_DOUBLE_EQ(received.resolution(), 0.05);
  const std::vector<uint8_t> got(received.data().begin(), received.data().end());
  EXPECT_EQ(got, bytes);
}

}  // namespace
}  // namespace mapmerge::wire
