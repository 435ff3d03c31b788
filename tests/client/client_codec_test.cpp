// Serialisation round trips on the real maps, without a network: the client's map updates
// (native MapUpdate, plain and zstd) and the ROS 2 messages (octomap_msgs/Octomap with the bare
// binary body, tf2_msgs/TFMessage) through their CDR encoding and back; poses as matrices.

#include <cmath>

#include <fastdds/rtps/common/SerializedPayload.h>
#include <gtest/gtest.h>
#include <octomap/OcTree.h>

#include "client_core.hpp"
#include "mapmerge/map/map_codec.hpp"
#include "mapmerge/map/map_io.hpp"
#include "mapmerge_fastdds/mapmergePubSubTypes.h"
#include "mapmerge_fastdds/ros2_msgsPubSubTypes.h"

namespace mapmerge {
namespace {

using client::detail::MapMessage;

/// Serialises `in` to CDR with its generated type support and deserialises it into a new sample.
template <class PubSubType, class Sample>
Sample cdr_round_trip(Sample& in) {
  PubSubType type;
  eprosima::fastrtps::rtps::SerializedPayload_t payload(type.getSerializedSizeProvider(&in)());
  EXPECT_TRUE(type.serialize(&in, &payload));
  Sample out;
  EXPECT_TRUE(type.deserialize(&payload, &out));
  return out;
}

void expect_same_tree(const octomap::OcTree& a, const octomap::OcTree& b) {
  EXPECT_EQ(a.size(), b.size());
  EXPECT_DOUBLE_EQ(a.getResolution(), b.getResolution());
  EXPECT_EQ(encode_map(a, Encoding::kOctomapBt), encode_map(b, Encoding::kOctomapBt));
}

class RealMap : public ::testing::TestWithParam<const char*> {
 protected:
  std::unique_ptr<octomap::OcTree> tree() const {
    return read_octree_file(std::string(MAPMERGE_DATA_DIR) + "/" + GetParam());
  }
};

TEST_P(RealMap, NativeMapUpdateRoundTripsThroughCdr) {
  const auto original = tree();
  for (const bool zstd : {false, true}) {
    SCOPED_TRACE(zstd ? "zstd" : "plain");
    client::Options options;
    options.robot_id = "r1";
    options.frame_id = "r1/map";
    options.zstd = zstd;
    const MapMessage m = client::detail::make_map_message(*original, options, "0123456789abcdef", 42);
    EXPECT_EQ(m.encoding, zstd ? "octomap-bt+zstd" : "octomap-bt");
    EXPECT_DOUBLE_EQ(m.resolution, original->getResolution());

    mapmerge::MapUpdate sample;
    sample.robot_id(m.robot_id);
    sample.session_id(m.session_id);
    sample.sequence_number(m.sequence_number);
    sample.stamp().sec(m.stamp_sec);
    sample.stamp().nanosec(m.stamp_nanosec);
    sample.frame_id(m.frame_id);
    sample.resolution(m.resolution);
    sample.encoding(m.encoding);
    sample.data(m.data);
    const auto back = cdr_round_trip<mapmerge::MapUpdatePubSubType>(sample);
    EXPECT_EQ(back, sample);
    EXPECT_EQ(back.data(), m.data);
    DecodeResult decoded = decode_map(back.data(), back.encoding(), DecodeLimits{});
    ASSERT_TRUE(decoded.ok()) << decoded.reason;
    expect_same_tree(*decoded.tree, *original);
  }
}

TEST_P(RealMap, GlobalMapDecodesPlainAndZstdAndRejectsAMislabelledPayload) {
  const auto original = tree();
  for (const Encoding encoding : {Encoding::kOctomapBt, Encoding::kOctomapBtZstd}) {
    client::detail::GlobalMapMessage m;
    m.version = 3;
    m.encoding = to_string(encoding);
    m.data = encode_map(*original, encoding);
    m.contributors.push_back({"r1", "s", 2});
    std::string error;
    const auto map = client::detail::decode_global_map(std::move(m), 100'000'000, error);
    ASSERT_TRUE(map) << error;
    EXPECT_EQ(map->version, 3u);
    ASSERT_EQ(map->contributors.size(), 1u);
    expect_same_tree(*map->tree, *original);
  }
  client::detail::GlobalMapMessage wrong;
  wrong.version = 4;
  wrong.encoding = "octomap-bt+zstd";
  wrong.data = encode_map(*original, Encoding::kOctomapBt);
  std::string error;
  EXPECT_FALSE(client::detail::decode_global_map(std::move(wrong), 100'000'000, error));
  EXPECT_NE(error.find("version 4"), std::string::npos) << error;
  client::detail::GlobalMapMessage big;
  big.encoding = "octomap-bt";
  big.data = encode_map(*original, Encoding::kOctomapBt);
  EXPECT_FALSE(client::detail::decode_global_map(std::move(big), 1000, error));
}

TEST_P(RealMap, RosOctomapMessageRoundTripsThroughCdr) {
  const auto original = tree();
  octomap_msgs::msg::dds_::Octomap_ msg;
  msg.header().frame_id("r3/map");
  msg.header().stamp().sec(1700000000);
  msg.header().stamp().nanosec(5);
  msg.binary(true);
  msg.id("OcTree");
  msg.resolution(original->getResolution());
  const auto body = encode_tree_body(*original, true);
  msg.data(std::vector<int8_t>(body.begin(), body.end()));
  const auto back = cdr_round_trip<octomap_msgs::msg::dds_::Octomap_PubSubType>(msg);
  EXPECT_EQ(back, msg);
  const std::vector<std::uint8_t> bytes(back.data().begin(), back.data().end());
  DecodeResult decoded = decode_tree_body(back.id(), back.resolution(), back.binary(), bytes, DecodeLimits{});
  ASSERT_TRUE(decoded.ok()) << decoded.reason;
  expect_same_tree(*decoded.tree, *original);
}

INSTANTIATE_TEST_SUITE_P(Data, RealMap, ::testing::Values("fr_079.bt", "fr_078_tidyup.bt", "geb079.bt"),
                         [](const auto& param_info) {
                           std::string name = param_info.param;
                           return name.substr(0, name.find('.'));
                         });

TEST(RosTf, TfMessageRoundTripsThroughCdr) {
  tf2_msgs::msg::dds_::TFMessage_ tf;
  for (const char* robot : {"r1", "r2"}) {
    geometry_msgs::msg::dds_::TransformStamped_ t;
    t.header().frame_id("global");
    t.header().stamp().sec(12);
    t.child_frame_id(std::string(robot) + "/map");
    t.transform().translation().x(1.5);
    t.transform().rotation().z(std::sqrt(0.5));
    t.transform().rotation().w(std::sqrt(0.5));
    tf.transforms().push_back(t);
  }
  const auto back = cdr_round_trip<tf2_msgs::msg::dds_::TFMessage_PubSubType>(tf);
  EXPECT_EQ(back, tf);
  ASSERT_EQ(back.transforms().size(), 2u);
  EXPECT_EQ(back.transforms()[1].child_frame_id(), "r2/map");
}

TEST(PoseMatrix, RowMajorHomogeneousAndNormalised) {
  client::Pose p;
  auto m = p.matrix();
  for (int i = 0; i < 16; ++i) EXPECT_DOUBLE_EQ(m[i], (i % 5 == 0) ? 1.0 : 0.0) << i;
  p.translation = {1, 2, 3};
  p.rotation = {0, 0, 2, 2};  // 90 degrees about z, not normalised
  m = p.matrix();
  const std::array<double, 16> expected{0, -1, 0, 1, 1, 0, 0, 2, 0, 0, 1, 3, 0, 0, 0, 1};
  for (int i = 0; i < 16; ++i) EXPECT_NEAR(m[i], expected[i], 1e-12) << i;
  p.rotation = {0, 0, 0, 0};  // degenerate: identity rotation, never NaN
  m = p.matrix();
  EXPECT_DOUBLE_EQ(m[0], 1.0);
  EXPECT_DOUBLE_EQ(m[3], 1.0);
}

TEST(Names, VendorsStatusesAndSessionIds) {
  EXPECT_EQ(client::parse_vendor("cyclone"), client::Vendor::kCyclone);
  EXPECT_EQ(client::parse_vendor("fastdds"), client::Vendor::kFastdds);
  EXPECT_FALSE(client::parse_vendor("opendds"));
  EXPECT_STREQ(client::to_string(client::PoseStatus::kAligned), "aligned");
  EXPECT_STREQ(client::to_string(client::PoseStatus::kRejected), "rejected");
  EXPECT_STREQ(client::to_string(client::PoseStatus::kUnknown), "unknown");
  const std::string& id = client::detail::process_session_id();
  EXPECT_EQ(id.size(), 16u);
  EXPECT_EQ(id.find_first_not_of("0123456789abcdef"), std::string::npos);
  EXPECT_EQ(&id, &client::detail::process_session_id());
}

}  // namespace
}  // namespace mapmerge
