// Fleets without multicast: the client and a (stand-in) server find each other through a Fast
// DDS discovery server (fast-discovery-server from fastdds-tools) on loopback.

#include <thread>

#include <gtest/gtest.h>
#include <octomap/OcTree.h>

#include "child_process.hpp"
#include "dds_test_env.hpp"
#include "fake_server.hpp"
#include "mapmerge/client/client.hpp"
#include "mapmerge/map/map_io.hpp"

namespace mapmerge {
namespace {

using namespace std::chrono_literals;

TEST(DiscoveryServer, ClientAndServerMeetThroughIt) {
  const int domain = test::dds_domain();
  const std::string port = std::to_string(30000 + domain);  // one port per test domain
  const std::string address = "127.0.0.1:" + port;
  const std::string logs = ::testing::TempDir() + "ds_" + std::to_string(::getpid());
  test::ChildProcess ds("/usr/bin/fast-discovery-server", {"-i", "0", "-l", "127.0.0.1", "-p", port},
                        test::Logs::split(logs));
  std::this_thread::sleep_for(500ms);
  ASSERT_TRUE(ds.running()) << ds.err();

  test::FakeServer server(domain, address);
  server.listen_to("r1");
  client::Options o;
  o.robot_id = "r1";
  o.domain = domain;
  o.discovery_server = address;
  Client robot(o);
  ASSERT_TRUE(robot.wait_for_server(30s));
  const auto tree = read_octree_file(std::string(MAPMERGE_DATA_DIR) + "/geb079.bt");
  ASSERT_TRUE(robot.publish(*tree).queued);
  const auto update = server.take_map("r1", 30s);
  ASSERT_TRUE(update);
  EXPECT_EQ(update->sequence_number(), 1u);
  ASSERT_TRUE(server.publish_pose(test::FakeServer::make_pose("r1", mapmerge::POSE_ALIGNED, {1, 0, 0}, {0, 0, 0, 1}, 1)));
  const auto deadline = std::chrono::steady_clock::now() + 30s;
  while (!robot.own_pose() && std::chrono::steady_clock::now() < deadline) std::this_thread::sleep_for(20ms);
  ASSERT_TRUE(robot.own_pose());
  EXPECT_EQ(robot.own_pose()->status, client::PoseStatus::kAligned);
  ds.signal(SIGTERM);
  ds.wait(10s);
}

TEST(DiscoveryServer, FastddsClientTakesItFromRosDiscoveryServer) {
  const int domain = test::dds_domain();
  const std::string port = std::to_string(30000 + domain);
  const std::string address = "127.0.0.1:" + port;
  test::ChildProcess ds("/usr/bin/fast-discovery-server", {"-i", "0", "-l", "127.0.0.1", "-p", port},
                        test::Logs::split(::testing::TempDir() + "ds_env_" + std::to_string(::getpid())));
  std::this_thread::sleep_for(500ms);
  ASSERT_TRUE(ds.running()) << ds.err();
  test::FakeServer server(domain, address);
  ::setenv("ROS_DISCOVERY_SERVER", address.c_str(), 1);
  client::Options o;
  o.robot_id = "r2";
  o.domain = domain;
  Client robot(o);
  ::unsetenv("ROS_DISCOVERY_SERVER");
  EXPECT_TRUE(robot.wait_for_server(30s));
  ds.signal(SIGTERM);
  ds.wait(10s);
}

TEST(DiscoveryServer, CycloneClientRejectsIt) {
  client::Options o;
  o.robot_id = "r1";
  o.domain = test::dds_domain();
  o.discovery_server = "127.0.0.1:11811";
  EXPECT_THROW(CycloneClient{o}, client::ClientError);
}

}  // namespace
}  // namespace mapmerge
