// mapmerge-server against updates that are well formed but do not fit: repeats and older
// updates, an empty map, two participants using one robot id, a robot mapping at another
// resolution. Each is logged and counted on the status topic; nobody else's data changes.

#include <octomap/OcTree.h>

#include "server_fixture.hpp"

namespace mapmerge::test {
namespace {

TEST_F(ServerFleet, RepeatedOlderAndEmptyUpdatesAreIgnoredOrRejectedAndCounted) {
  auto server = start_server();
  RobotPublisher r1(domain, "r1");
  r1.publish(*fleet().robots[0].tree, "s1", 1);
  FleetListener op(domain);
  ASSERT_TRUE(op.wait_for([&] { return global_has(op, 1); }, kMergeTimeout)) << server->log();

  // The same update again (a republish, a client's resend) and, once update 5 is held, update 4.
  r1.publish(*fleet().robots[0].tree, "s1", 1);
  ASSERT_TRUE(op.wait_for([&] { return op.status().ignored["r1"] >= 1; }, 60s)) << server->log();
  r1.publish(*fleet().robots[0].tree, "s1", 5);
  ASSERT_TRUE(op.wait_for([&] { return op.status().sequence["r1"] == 5; }, 60s)) << server->log();
  r1.publish(*fleet().robots[1].tree, "s1", 4);
  ASSERT_TRUE(op.wait_for([&] { return op.status().ignored["r1"] >= 2; }, 60s)) << server->log();
  EXPECT_GE(op.status().updates_ignored, 2u);
  EXPECT_NE(server->log().find("update s1/4 ignored: older than the update held"), std::string::npos)
      << server->log();
  EXPECT_EQ(op.status().sequence["r1"], 5u);
  EXPECT_EQ(op.status().rejected["r1"], 0u);

  // An empty map is a valid stream, and no map: rejected with its reason.
  RobotPublisher empty(domain, "r2");
  empty.publish(octomap::OcTree(fleet().robots[0].tree->getResolution()), "s1", 1);
  ASSERT_TRUE(op.wait_for([&] { return op.status().rejected["r2"] >= 1; }, 60s)) << server->log();
  EXPECT_EQ(op.status().last_error["r2"], "empty map");
  EXPECT_EQ(op.status().accepted["r2"], 0u);
  EXPECT_EQ(op.global().contributors, std::vector<std::string>{"r1"});
  EXPECT_TRUE(server->running());
}

TEST_F(ServerFleet, TwoParticipantsUsingOneRobotIdAreReportedAndDoNotTakeTurns) {
  auto server = start_server({"--reference", "r1"});
  RobotPublisher r1(domain, "r1");
  r1.publish(*fleet().robots[0].tree, "s1", 1);
  FleetListener op(domain);
  ASSERT_TRUE(op.wait_for([&] { return global_has(op, 1); }, kMergeTimeout)) << server->log();

  RobotPublisher first(domain, "r2"), second(domain, "r2");
  const auto session = [&] { return op.status().session["r2"]; };
  first.publish(*fleet().robots[1].tree, "a", 1);
  ASSERT_TRUE(op.wait_for([&] { return session() == "a"; }, 60s)) << server->log();
  second.publish(*fleet().robots[2].tree, "b", 1);  // to the server, this is r2 restarted
  ASSERT_TRUE(op.wait_for([&] { return session() == "b"; }, 60s)) << server->log();
  first.publish(*fleet().robots[1].tree, "a", 2);   // but session a still publishes: two participants
  ASSERT_TRUE(op.wait_for([&] { return op.status().rejected["r2"] >= 1; }, 60s)) << server->log();
  EXPECT_NE(op.status().last_error["r2"].find("used by two participants"), std::string::npos)
      << op.status().last_error["r2"];
  EXPECT_NE(server->log().find("robot id r2 is used by two participants: session a was replaced by session b"),
            std::string::npos) << server->log();
  // The session in force keeps the id: its next update is taken, the other's are not.
  second.publish(*fleet().robots[2].tree, "b", 2);
  first.publish(*fleet().robots[1].tree, "a", 3);
  ASSERT_TRUE(op.wait_for([&] { return op.status().sequence["r2"] == 2 && op.status().rejected["r2"] >= 2; }, 60s))
      << server->log();
  EXPECT_EQ(session(), "b");
  EXPECT_EQ(op.status().accepted["r1"], 1u);  // nobody else's data changed
  EXPECT_TRUE(server->running());
}

TEST_F(ServerFleet, RobotMappingAtACoarserResolutionIsAlignedAndFusedResampled) {
  auto server = start_server({"--reference", "r1"});
  RobotPublisher r1(domain, "r1");
  r1.publish(*fleet().robots[0].tree);
  const std::shared_ptr<const octomap::OcTree> coarse = mapmerge::coarsen(*fleet().robots[1].tree, 2);
  RobotPublisher r2(domain, "r2");
  r2.publish(*coarse);
  FleetListener op(domain);
  ASSERT_TRUE(op.wait_for([&] { return aligned(op, {"r1", "r2"}) && global_has(op, 2); }, kMergeTimeout))
      << server->log();
  const auto pose = op.poses().at("r2");
  EXPECT_LT(rotation_error_deg(fleet().truth(1), pose.T_global_robot), kMaxRotationDeg);
  EXPECT_LT(translation_error_m(fleet().truth(1), pose.T_global_robot), kMaxTranslationM);
  // The status topic is periodic: the one that shows r2's map may come after its pose.
  ASSERT_TRUE(op.wait_for([&] { return op.status().resolution["r2"] > 0.0; }, 30s)) << server->log();
  EXPECT_DOUBLE_EQ(op.status().resolution["r2"], coarse->getResolution());
  EXPECT_NE(server->log().find("differs from the reference's"), std::string::npos) << server->log();
  const auto global = op.global();
  EXPECT_DOUBLE_EQ(global.tree->getResolution(), fleet().robots[0].tree->getResolution());
  EXPECT_GT(occupied_coverage(*global.tree, *coarse, fleet().truth(1)), 0.8);
}

}  // namespace
}  // namespace mapmerge::test
