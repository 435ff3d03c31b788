// mapmerge-server end to end: a real server process, robots and an operator as real Fast DDS
// participants on loopback (the `local` profile), real SQLite state, real maps cut from data/.

#include "server_fixture.hpp"

namespace mapmerge::test {
namespace {

using Box = Eigen::AlignedBox3d;

TEST_F(ServerFleet, ThreeRobotsAreAlignedAndAStrangerStaysUnknown) {
  auto server = start_server({"--reference", "r1"});
  const Fleet& f = fleet();
  std::vector<std::unique_ptr<RobotPublisher>> pubs;
  for (const auto& r : f.robots) {
    pubs.push_back(std::make_unique<RobotPublisher>(domain, r.id));
    pubs.back()->publish(*r.tree);
  }
  const auto stranger_world = load_data_map("fr_078_tidyup.bt");
  const auto stranger = cut_robot_map(*stranger_world, "r4", Box(Eigen::Vector3d(-10, -8, -2), Eigen::Vector3d(2, 6, 4)),
                                      mapmerge::paper_transform(0, 0, 0, 0, 0, 45));
  RobotPublisher r4(domain, "r4");
  r4.publish(*stranger.tree);

  FleetListener op(domain);
  ASSERT_TRUE(op.wait_for([&] { return aligned(op, {"r1", "r2", "r3"}) && global_has(op, 3); }, kMergeTimeout))
      << server->log();
  for (std::size_t i = 1; i < f.robots.size(); ++i) {
    const auto pose = op.poses().at(f.robots[i].id);
    EXPECT_LT(rotation_error_deg(f.truth(i), pose.T_global_robot), kMaxRotationDeg) << f.robots[i].id;
    EXPECT_LT(translation_error_m(f.truth(i), pose.T_global_robot), kMaxTranslationM) << f.robots[i].id;
  }
  // The global map (in r1's frame) covers every robot's occupied cells.
  ASSERT_TRUE(op.wait_for([&] { return op.global().contributors.size() == 3; }, 30s));
  const auto global = op.global();
  for (std::size_t i = 0; i < f.robots.size(); ++i) {
    EXPECT_GT(occupied_coverage(*global.tree, *f.robots[i].tree, f.truth(i)), 0.9) << f.robots[i].id;
  }
  // The stranger was tried against the group, is reported unknown and is not fused.
  const auto tried_r4 = [&] {
    std::size_t n = 0;
    for (const auto& m : op.merges()) n += m.source == "r4" ? 1 : 0;
    return n;
  };
  const auto r4_accepted = [&] {
    for (const auto& m : op.merges()) {
      if (m.source == "r4" && m.accepted) return true;
    }
    return false;
  };
  ASSERT_TRUE(op.wait_for([&] { return tried_r4() >= 3 || r4_accepted(); }, kMergeTimeout)) << server->log();
  for (const auto& m : op.merges()) {
    if (m.source == "r4") {
      EXPECT_FALSE(m.accepted) << "r4 merged into " << m.target;
    }
  }
  ASSERT_TRUE(op.wait_for([&] { return op.poses().count("r4") == 1; }, 30s));
  EXPECT_EQ(op.poses().at("r4").status, 0);
  for (const auto& c : op.global().contributors) {
    EXPECT_NE(c, "r4");
  }
  EXPECT_GT(op.ros_global_bytes(), 0u);
  EXPECT_TRUE(op.wait_for([&] { return op.tf_children().size() >= 3; }, 10s));
  EXPECT_EQ(server->kill(SIGTERM), 0) << server->log();
}

}  // namespace
}  // namespace mapmerge::test
