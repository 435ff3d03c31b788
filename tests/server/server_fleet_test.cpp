// mapmerge-server end to end: a real server process, robots and an operator as real Fast DDS
// participants on loopback (the `local` profile), real SQLite state, real maps cut from data/.

#include <gtest/gtest.h>

#include "dds_test_env.hpp"
#include "fleet.hpp"
#include "mapmerge/align/map_cut.hpp"
#include "server_process.hpp"

namespace mapmerge::test {
namespace {

using namespace std::chrono_literals;
using Box = Eigen::AlignedBox3d;
namespace ma = mapmerge::align;

constexpr auto kMergeTimeout = 120s;  ///< generous: 2 shared cores, alignment of real maps
constexpr double kMaxRotationDeg = 2.0;
constexpr double kMaxTranslationM = 0.3;  ///< ~4 voxels of geb079 (8 cm), after chaining two merges

Box box(double x0, double x1) { return Box(Eigen::Vector3d(x0, -8, -1), Eigen::Vector3d(x1, 8, 4)); }

/// Three robots along the geb079 corridor (8 cm), overlapping their neighbours by 8-10 m, each
/// in a random frame; and a stranger from another building.
struct Fleet {
  std::shared_ptr<const octomap::OcTree> world = load_data_map("geb079.bt");
  std::vector<RobotMap> robots{
      cut_robot_map(*world, "r1", box(-8, 12), ma::make_transform(1, 2, 0, 0, 0, 30)),
      cut_robot_map(*world, "r2", box(4, 24), ma::make_transform(-4, 7, 0.3, -3, 2, 155)),
      cut_robot_map(*world, "r3", box(14, 31), ma::make_transform(5, -3, 0.2, 2, -1, -70))};
  /// The truth: T_global_robot = T_r1_world * T_robot_world^-1.
  Eigen::Matrix4d truth(std::size_t i) const {
    return robots[0].T_robot_world * robots[i].T_robot_world.inverse();
  }
};

const Fleet& fleet() {
  static const Fleet f;
  return f;
}

class ServerFleet : public ::testing::Test {
 protected:
  int domain = dds_domain();
  std::string dir = temp_dir(::testing::UnitTest::GetInstance()->current_test_info()->name());

  std::unique_ptr<ServerProcess> start_server(std::vector<std::string> extra = {}) {
    std::vector<std::string> args{"--domain", std::to_string(domain), "--profile", "local",
                                  "--state-dir", dir + "/state"};
    args.insert(args.end(), extra.begin(), extra.end());
    return std::make_unique<ServerProcess>(args, dir + "/server.log");
  }
  static bool aligned(const FleetListener& l, const std::vector<std::string>& ids) {
    const auto poses = l.poses();
    for (const auto& id : ids) {
      auto it = poses.find(id);
      if (it == poses.end() || it->second.status != 1) return false;
    }
    return true;
  }
  static bool global_has(const FleetListener& l, std::size_t contributors) {
    return l.global().contributors.size() >= contributors;
  }
};

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
                                      ma::make_transform(0, 0, 0, 0, 0, 45));
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
  ASSERT_TRUE(op.wait_for([&] { return tried_r4() >= 3; }, kMergeTimeout)) << server->log();
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
