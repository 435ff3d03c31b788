// mapmerge-server over its life: late joiners, map requests, restart after SIGKILL, bursts,
// a discovery server, ROS 2 robots and bad input. Real processes on loopback, real SQLite.

#include <fstream>

#include "mapmerge/map/map_codec.hpp"

#include "server_fixture.hpp"

namespace mapmerge::test {
namespace {

/// r1 and r2 published and merged; returns the operator's view once both are in the global map.
void merge_two(int domain, FleetListener& op, const ServerProcess& server,
               std::vector<std::unique_ptr<RobotPublisher>>& pubs) {
  for (std::size_t i = 0; i < 2; ++i) {
    pubs.push_back(std::make_unique<RobotPublisher>(domain, fleet().robots[i].id));
    pubs.back()->publish(*fleet().robots[i].tree);
  }
  ASSERT_TRUE(op.wait_for([&] { return op.global().contributors.size() == 2; }, kMergeTimeout)) << server.log();
}

TEST_F(ServerFleet, LateJoinerReceivesTheGlobalMapAndPoses) {
  auto server = start_server();
  std::vector<std::unique_ptr<RobotPublisher>> pubs;
  {
    FleetListener early(domain);
    merge_two(domain, early, *server, pubs);
  }
  FleetListener late(domain);  // joins after the map was published
  ASSERT_TRUE(late.wait_for([&] { return global_has(late, 2) && aligned(late, {"r1", "r2"}); }, 30s)) << server->log();
  EXPECT_GT(late.global().tree->getNumLeafNodes(), 1000u);
  EXPECT_EQ(late.poses().at("r2").global_version, late.global().version);
}

TEST_F(ServerFleet, MapRequestIsAnsweredAtOnce) {
  const std::string config = dir + "/server.yaml";
  std::ofstream(config) << "publish:\n  republish_period_s: 3600\n  min_interval_s: 0.1\nmerge:\n  threads: 2\n";
  auto server = start_server({"--config", config});
  std::vector<std::unique_ptr<RobotPublisher>> pubs;
  std::uint64_t version = 0;
  {
    FleetListener early(domain);
    merge_two(domain, early, *server, pubs);
    version = early.global().version;
  }
  FleetListener late(domain);
  ASSERT_TRUE(late.wait_for([&] { return late.global().version >= version; }, 30s)) << server->log();
  // Nothing changes and the periodic republish is an hour away: only an answer to the request
  // brings the map again.
  const auto before = late.globals_received();
  ASSERT_TRUE(late.wait_for([&] {
    late.request();  // volatile: repeated until the server's reader has matched
    return late.globals_received() > before;
  }, 30s)) << server->log();
  EXPECT_NE(server->log().find("map request from fleet_listener"), std::string::npos);
  EXPECT_EQ(late.global().version, version);
}

TEST_F(ServerFleet, RestartAfterKillRestoresTheGlobalMapAndPoses) {
  auto server = start_server();
  std::uint64_t version = 0;
  std::map<std::string, ReceivedPose> poses;
  {
    std::vector<std::unique_ptr<RobotPublisher>> pubs;
    FleetListener op(domain);
    merge_two(domain, op, *server, pubs);
    ASSERT_TRUE(op.wait_for([&] { return aligned(op, {"r1", "r2"}); }, 30s));
    version = op.global().version;
    poses = op.poses();
  }  // the robots are gone: nobody will republish
  EXPECT_EQ(server->kill(SIGKILL), 128 + SIGKILL);
  clean_shm();
  auto restarted = start_server();
  FleetListener op(domain);
  ASSERT_TRUE(op.wait_for([&] { return op.global().version >= version && aligned(op, {"r1", "r2"}); }, 30s))
      << restarted->log();
  EXPECT_EQ(op.global().version, version);
  EXPECT_EQ(op.global().contributors.size(), 2u);
  for (const auto& id : {"r1", "r2"}) {
    // Identical up to the quaternion round trip of the wire.
    EXPECT_LT((poses.at(id).T_global_robot - op.poses().at(id).T_global_robot).norm(), 1e-9) << id;
  }
  EXPECT_EQ(restarted->kill(SIGTERM), 0);
}

TEST_F(ServerFleet, BurstOfFiftyUpdatesIsCoalescedAndTheLastOneFused) {
  auto server = start_server({"--reference", "r1"});  // r2 is a known robot: its updates are refined
  std::vector<std::unique_ptr<RobotPublisher>> pubs;
  FleetListener op(domain);
  merge_two(domain, op, *server, pubs);
  // r2 keeps mapping: 49 quick repeats of its map, then a grown map (the corridor up to x = 31).
  const auto grown = cut_robot_map(*fleet().world, "r2", strip(4, 31), fleet().robots[1].T_robot_world);
  for (std::uint64_t seq = 2; seq <= 50; ++seq) pubs[1]->publish(seq < 50 ? *fleet().robots[1].tree : *grown.tree, "s1", seq);
  ASSERT_TRUE(op.wait_for([&] { return op.global().contributor_sequence["r2"] == 50; }, kMergeTimeout))
      << server->log();
  EXPECT_GT(global_coverage_after(op, *grown.tree, fleet().truth(1), 0.9, kMergeTimeout), 0.9) << server->log();
  // The map topic keeps the latest sample per robot (KEEP_LAST 1): under load DDS may replace
  // samples of the burst before they are sent, so only the last one is sure to arrive. Wait for
  // the status of the server holding it.
  ASSERT_TRUE(op.wait_for([&] {
    const auto st = op.status();
    return st.sequence.count("r2") != 0 && st.sequence.at("r2") == 50;
  }, kMergeTimeout)) << server->log();
  const auto s = op.status();
  EXPECT_GE(s.updates_received, 3u);  // r1's map, r2's first and its last
  EXPECT_LE(s.updates_received, 51u);
  EXPECT_LE(s.accepted.at("r2"), 50u);
  // Every received update was merged, coalesced away, or ignored as stale: none waits in a queue.
  EXPECT_LE(s.accepted.at("r1") + s.accepted.at("r2") + s.merges_coalesced, s.updates_received);
  RecordProperty("r2_updates_processed", static_cast<int>(s.accepted.at("r2")));
  RecordProperty("merges_coalesced", static_cast<int>(s.merges_coalesced));
}

TEST_F(ServerFleet, DiscoveryServerOnLoopback) {
  const int port = 21000 + domain;
  ChildProcess discovery("fastdds", {"discovery", "-i", "0", "-l", "127.0.0.1", "-p", std::to_string(port)},
                         Logs::combined(dir + "/discovery.log"));
  const std::string address = "127.0.0.1:" + std::to_string(port);
  auto server = start_server({"--discovery-server", address});
  wire::ProfileSpec profile;
  profile.discovery_server = address;
  FleetListener op(domain, profile);
  std::vector<std::unique_ptr<RobotPublisher>> pubs;
  for (std::size_t i = 0; i < 2; ++i) {
    pubs.push_back(std::make_unique<RobotPublisher>(domain, fleet().robots[i].id, profile));
    pubs.back()->publish(*fleet().robots[i].tree);
  }
  ASSERT_TRUE(op.wait_for([&] { return global_has(op, 2) && aligned(op, {"r1", "r2"}); }, kMergeTimeout))
      << server->log() << discovery.log();
  EXPECT_EQ(server->kill(SIGTERM), 0);
  discovery.kill(SIGINT);
}

TEST_F(ServerFleet, Ros2OctomapRobotJoins) {
  auto server = start_server({"--reference", "r1"});
  RobotPublisher r1(domain, "r1");
  r1.publish(*fleet().robots[0].tree);
  RosRobotPublisher r2(domain, "r2");
  r2.publish(*fleet().robots[1].tree);
  FleetListener op(domain);
  ASSERT_TRUE(op.wait_for([&] { return global_has(op, 2) && aligned(op, {"r1", "r2"}); }, kMergeTimeout))
      << server->log();
  EXPECT_LT(rotation_error_deg(fleet().truth(1), op.poses().at("r2").T_global_robot), kMaxRotationDeg);
  EXPECT_LT(translation_error_m(fleet().truth(1), op.poses().at("r2").T_global_robot), kMaxTranslationM);
  EXPECT_TRUE(op.wait_for([&] { return op.tf_children().size() >= 2; }, 10s));
  EXPECT_GT(op.ros_global_bytes(), 1000u);
}

TEST_F(ServerFleet, RobotHeardBeforeTheReferenceIsAlignedWhenItArrives) {
  auto server = start_server({"--reference", "r1"});
  FleetListener op(domain);
  RobotPublisher r2(domain, "r2");
  r2.publish(*fleet().robots[1].tree);
  ASSERT_TRUE(op.wait_for([&] { return op.poses().count("r2") == 1; }, 60s)) << server->log();
  EXPECT_EQ(op.poses().at("r2").status, 0);  // nothing to align with yet
  RobotPublisher r1(domain, "r1");
  r1.publish(*fleet().robots[0].tree);
  ASSERT_TRUE(op.wait_for([&] { return aligned(op, {"r1", "r2"}) && global_has(op, 2); }, kMergeTimeout))
      << server->log();
  EXPECT_LT(translation_error_m(fleet().truth(1), op.poses().at("r2").T_global_robot), kMaxTranslationM);
}

TEST_F(ServerFleet, BadMapsAreRejectedAndCountedWithoutHarm) {
  auto server = start_server();
  RobotPublisher r1(domain, "r1");
  r1.publish(*fleet().robots[0].tree);
  FleetListener op(domain);
  ASSERT_TRUE(op.wait_for([&] { return global_has(op, 1); }, kMergeTimeout)) << server->log();
  const auto version = op.global().version;
  RobotPublisher bad(domain, "r2");
  bad.publish_bytes(std::vector<std::uint8_t>(200000, 0xFF), "r2", "s1", 1);  // garbage
  RobotPublisher liar(domain, "r3");
  liar.publish_bytes(encode_map(*fleet().robots[1].tree, Encoding::kOctomapBt), "r1", "s1", 1);  // r1's id on r3's topic
  ASSERT_TRUE(op.wait_for([&] { return op.status().rejected["r2"] >= 1 && op.status().rejected["r3"] >= 1; }, 60s))
      << server->log();
  EXPECT_FALSE(op.status().last_error["r2"].empty());
  EXPECT_NE(op.status().last_error["r3"].find("does not match"), std::string::npos);
  EXPECT_EQ(op.status().accepted["r1"], 1u);
  EXPECT_EQ(op.global().version, version);
  EXPECT_TRUE(server->running());
}

}  // namespace
}  // namespace mapmerge::test
