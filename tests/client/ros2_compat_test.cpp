// ROS 2 compatibility on the wire, with no ROS 2 installed: a hand-written Cyclone DDS (C API)
// participant behaves as a ROS 2 node does (topics with the "rt/" prefix, ROS 2's DDS type names
// and field layout, ROS 2's default QoS): it publishes a real map as octomap_msgs/Octomap on
// rt/<robot>/octomap_binary, as octomap_server does; the real Fast DDS mapmerge-server takes it
// in as a robot, aligns it, and the same participant receives the robot's frame as
// tf2_msgs/TFMessage on rt/tf and the global map as octomap_msgs/Octomap.

#include <thread>

#include <gtest/gtest.h>
#include <octomap/OcTree.h>

#include "mapmerge/client/client.hpp"
#include "mapmerge/map/map_codec.hpp"
#include "mapmerge/map/map_io.hpp"
#include "mapmerge/wire/cyclone.hpp"
#include "mapmerge/wire/topics.hpp"
#include "mapmerge_cyclone/ros2_msgs.h"
#include "server_fixture.hpp"

namespace mapmerge {
namespace {

using namespace std::chrono_literals;
constexpr auto kAlignment = 150s;

/// QoS of a ROS 2 endpoint (rclcpp's QoS(depth) with reliability/durability set, as the
/// publishers and subscribers named below create them).
dds_qos_t* ros2_qos(bool transient_local, int32_t depth) {
  dds_qos_t* qos = dds_create_qos();
  dds_qset_reliability(qos, DDS_RELIABILITY_RELIABLE, DDS_MSECS(100));
  dds_qset_durability(qos, transient_local ? DDS_DURABILITY_TRANSIENT_LOCAL : DDS_DURABILITY_VOLATILE);
  dds_qset_history(qos, DDS_HISTORY_KEEP_LAST, depth);
  return qos;
}

/// A ROS 2 node on Cyclone DDS, by hand: octomap_server's latched publisher of the robot's map
/// (QoS(1).transient_local()), tf2_ros::TransformListener's subscription on rt/tf (reliable,
/// volatile, depth 100) and RViz's octomap display subscribing the global map (transient local).
class Ros2Node {
 public:
  Ros2Node(int domain, const std::string& robot) : participant_(domain, wire::ProfileSpec{}) {
    const dds_entity_t p = participant_.participant();
    dds_qos_t* latched = ros2_qos(true, 1);
    dds_qos_t* tf_qos = ros2_qos(false, 100);
    map_writer_ = dds_create_writer(p, participant_.topic(&octomap_msgs_msg_dds__Octomap__desc, wire::ros_octomap_topic(robot)),
                                    latched, nullptr);
    tf_reader_ = dds_create_reader(p, participant_.topic(&tf2_msgs_msg_dds__TFMessage__desc, wire::kTfTopic), tf_qos, nullptr);
    global_reader_ = dds_create_reader(
        p, participant_.topic(&octomap_msgs_msg_dds__Octomap__desc, wire::kRosGlobalMapTopic), latched, nullptr);
    dds_delete_qos(latched);
    dds_delete_qos(tf_qos);
  }
  bool ok() const { return map_writer_ > 0 && tf_reader_ > 0 && global_reader_ > 0; }

  /// octomap_msgs::binaryMapToMsg: id "OcTree", binary, the bare writeBinaryData body.
  bool publish_map(const octomap::OcTree& tree, const std::string& frame) {
    std::vector<std::uint8_t> body = encode_tree_body(tree, true);
    octomap_msgs_msg_dds__Octomap_ msg{};
    msg.header.stamp.sec = 1700000000;
    msg.header.frame_id = const_cast<char*>(frame.c_str());
    msg.binary = true;
    msg.id = const_cast<char*>("OcTree");
    msg.resolution = tree.getResolution();
    msg.data._buffer = reinterpret_cast<int8_t*>(body.data());
    msg.data._length = static_cast<uint32_t>(body.size());
    msg.data._maximum = msg.data._length;
    msg.data._release = false;
    return dds_write(map_writer_, &msg) >= 0;
  }

  struct Transform {
    std::string parent, child;
    std::array<double, 16> matrix{};
  };
  /// Every transform received on rt/tf so far.
  std::vector<Transform> take_tf() {
    std::vector<Transform> out;
    take<tf2_msgs_msg_dds__TFMessage_>(tf_reader_, [&](const tf2_msgs_msg_dds__TFMessage_& m) {
      for (uint32_t i = 0; i < m.transforms._length; ++i) {
        const auto& t = m.transforms._buffer[i];
        client::Pose p;  // reuse the client's quaternion -> matrix
        p.translation = {t.transform.translation.x, t.transform.translation.y, t.transform.translation.z};
        p.rotation = {t.transform.rotation.x, t.transform.rotation.y, t.transform.rotation.z, t.transform.rotation.w};
        out.push_back({t.header.frame_id, t.child_frame_id, p.matrix()});
      }
    });
    return out;
  }

  struct RosMap {
    std::string id, frame;
    bool binary = false;
    double resolution = 0.0;
    std::vector<std::uint8_t> data;
  };
  std::optional<RosMap> take_global_map() {
    std::optional<RosMap> out;
    take<octomap_msgs_msg_dds__Octomap_>(global_reader_, [&](const octomap_msgs_msg_dds__Octomap_& m) {
      const auto* bytes = reinterpret_cast<const std::uint8_t*>(m.data._buffer);
      out = RosMap{m.id, m.header.frame_id, m.binary, m.resolution,
                   std::vector<std::uint8_t>(bytes, bytes + m.data._length)};
    });
    return out;
  }

 private:
  template <class Sample, class Sink>
  static void take(dds_entity_t reader, Sink&& sink) {
    for (;;) {
      void* samples[1] = {nullptr};
      dds_sample_info_t info;
      const dds_return_t n = dds_take(reader, samples, &info, 1, 1);
      if (n <= 0) return;
      if (info.valid_data) sink(*static_cast<const Sample*>(samples[0]));
      dds_return_loan(reader, samples, n);
    }
  }

  wire::CycloneParticipant participant_;
  dds_entity_t map_writer_ = 0;
  dds_entity_t tf_reader_ = 0;
  dds_entity_t global_reader_ = 0;
};

class Ros2Compat : public test::ServerFixture {};

TEST_F(Ros2Compat, CycloneRos2NodeJoinsAndReceivesTfAndTheGlobalMap) {
  start_server();
  // r1 is a mapmerge robot (the reference); r2 a ROS 2 robot running octomap_server on Cyclone.
  client::Options o1;
  o1.robot_id = "r1";
  o1.domain = test::dds_domain();
  Client r1(o1);
  const auto map1 = read_octree_file(map_path("r1"));
  ASSERT_TRUE(r1.publish(*map1).queued);

  Ros2Node node(test::dds_domain(), "r2");
  ASSERT_TRUE(node.ok());
  const auto map2 = read_octree_file(map_path("r2"));
  ASSERT_TRUE(node.publish_map(*map2, "r2/map"));

  const double r1_volume = test::occupied_volume(*map1);
  std::optional<Ros2Node::Transform> tf;
  std::optional<Ros2Node::RosMap> global;
  const auto deadline = std::chrono::steady_clock::now() + kAlignment;
  while (std::chrono::steady_clock::now() < deadline && !(tf && global && global->data.size() > 0)) {
    for (auto& t : node.take_tf()) {
      if (t.child == "r2/map") tf = t;
    }
    if (auto g = node.take_global_map()) {
      // Wait for a version holding both robots: one holding r1 alone may still arrive after r2's
      // transform (a republish, or a build under load).
      if (tf) {
        DecodeResult d = decode_tree_body(g->id, g->resolution, g->binary, g->data, DecodeLimits{});
        if (d.ok() && test::occupied_volume(*d.tree) > 1.2 * r1_volume) global = g;
      }
    }
    std::this_thread::sleep_for(50ms);
  }
  ASSERT_TRUE(tf) << "no rt/tf transform for r2/map\n" << server_log();
  EXPECT_EQ(tf->parent, "global");
  const auto error = test::pose_error(true_pose("r2"), tf->matrix);
  EXPECT_LT(error.rotation_deg, kMaxRotationErrorDeg);
  EXPECT_LT(error.translation_m, kMaxTranslationErrorM);

  // The global map, as octomap_rviz_plugins reads it (octomap_msgs::binaryMsgToMap).
  ASSERT_TRUE(global) << "no global map holding r2's strip too on " << wire::kRosGlobalMapTopic << "\n"
                      << server_log();
  EXPECT_EQ(global->id, "OcTree");
  EXPECT_TRUE(global->binary);
  EXPECT_EQ(global->frame, "global");
  DecodeResult decoded = decode_tree_body(global->id, global->resolution, global->binary, global->data, DecodeLimits{});
  ASSERT_TRUE(decoded.ok()) << decoded.reason;

  // The ROS 2 robot is a robot like any other on the native pose topic too.
  ASSERT_TRUE(r1.wait_for_server(10s));
  const auto deadline2 = std::chrono::steady_clock::now() + 30s;
  while (std::chrono::steady_clock::now() < deadline2 &&
         !(r1.pose("r2") && r1.pose("r2")->status == client::PoseStatus::kAligned)) {
    std::this_thread::sleep_for(50ms);
  }
  ASSERT_TRUE(r1.pose("r2"));
  EXPECT_EQ(r1.pose("r2")->status, client::PoseStatus::kAligned);
}

}  // namespace
}  // namespace mapmerge
