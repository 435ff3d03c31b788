// mapmerge-robot and mapmerge-listen as the demo and users run them, against a stand-in server:
// exit codes, flushed JSON lines, the saved global map, no library chatter on the output.

#include <filesystem>
#include <sstream>

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>
#include <octomap/OcTree.h>

#include "child_process.hpp"
#include "dds_test_env.hpp"
#include "fake_server.hpp"
#include "mapmerge/map/map_codec.hpp"
#include "mapmerge/map/map_io.hpp"

namespace mapmerge {
namespace {

using namespace std::chrono_literals;
namespace fs = std::filesystem;

const std::string kRobot = std::string(MAPMERGE_BINARY_DIR) + "/bin/mapmerge-robot";
const std::string kListen = std::string(MAPMERGE_BINARY_DIR) + "/bin/mapmerge-listen";
const std::string kData = MAPMERGE_DATA_DIR;
constexpr auto kDelivery = 20s;
constexpr auto kExit = 30s;

std::vector<nlohmann::json> json_lines(const std::string& text) {
  std::vector<nlohmann::json> lines;
  std::istringstream in(text);
  for (std::string line; std::getline(in, line);) {
    if (!line.empty()) lines.push_back(nlohmann::json::parse(line));  // throws on a non-JSON line
  }
  return lines;
}

class Cli : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() / ("mapmerge_cli_" + std::to_string(::getpid()) + "_" +
                                        ::testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::remove_all(dir_);
    fs::create_directories(dir_);
  }
  void TearDown() override { fs::remove_all(dir_); }
  std::string domain() const { return std::to_string(test::dds_domain()); }
  std::string log(const std::string& name) const { return (dir_ / name).string(); }
  fs::path dir_;
};

TEST_F(Cli, RobotPublishesAndExitsWhenAligned) {
  for (const std::string vendor : {"fastdds", "cyclone"}) {
    SCOPED_TRACE(vendor);
    const std::string id = "r_" + vendor;
    test::FakeServer server(test::dds_domain());
    server.listen_to(id);
    test::ChildProcess robot(kRobot,
                             {"--id", id, "--map", kData + "/geb079.bt", "--domain", domain(), "--vendor", vendor,
                              "--zstd", "--json", "--exit-when-aligned", "--timeout", "60"},
                             test::Logs::split(log("robot_" + vendor)));
    const auto update = server.take_map(id, kDelivery);
    ASSERT_TRUE(update) << robot.err();
    EXPECT_EQ(update->encoding(), "octomap-bt+zstd");
    EXPECT_EQ(update->sequence_number(), 1u);
    ASSERT_TRUE(server.publish_pose(
        test::FakeServer::make_pose(id, mapmerge::POSE_ALIGNED, {1, 2, 3}, {0, 0, 0, 1}, 4)));
    ASSERT_EQ(robot.wait(kExit), 0) << robot.err();
    const auto lines = json_lines(robot.out());
    ASSERT_EQ(lines.size(), 1u) << robot.out();
    EXPECT_EQ(lines[0]["robot"], id);
    EXPECT_EQ(lines[0]["status"], "aligned");
    EXPECT_EQ(lines[0]["global_version"], 4);
    EXPECT_EQ(lines[0]["T_global_robot"][3], 1.0);
    EXPECT_EQ(robot.err().find("Writing"), std::string::npos) << robot.err();
  }
}

class CliListen : public Cli, public ::testing::WithParamInterface<const char*> {};

TEST_P(CliListen, PrintsJsonPosesAndSavesTheGlobalMap) {
  test::FakeServer server(test::dds_domain());
  const auto tree = read_octree_file(kData + "/fr_078_tidyup.bt");
  const double s = std::sqrt(0.5);
  ASSERT_TRUE(server.publish_pose(test::FakeServer::make_pose("r1", mapmerge::POSE_ALIGNED, {0, 0, 0}, {0, 0, 0, 1}, 5)));
  ASSERT_TRUE(server.publish_pose(test::FakeServer::make_pose("r2", mapmerge::POSE_ALIGNED, {4, 5, 6}, {0, 0, s, s}, 5)));
  ASSERT_TRUE(server.publish_pose(test::FakeServer::make_pose("r3", mapmerge::POSE_UNKNOWN, {0, 0, 0}, {0, 0, 0, 1}, 5)));
  ASSERT_TRUE(server.publish_global(encode_map(*tree, Encoding::kOctomapBt), "octomap-bt", 5, {"r1", "r2"}));
  const std::string out = (dir_ / "global.bt").string();
  test::ChildProcess listen(kListen,
                            {"--domain", domain(), "--vendor", GetParam(), "--json", "--until-aligned", "2", "-o", out,
                             "--timeout", "60"},
                            test::Logs::split(log("listen")));
  ASSERT_EQ(listen.wait(kExit), 0) << listen.err();
  const auto lines = json_lines(listen.out());
  ASSERT_GE(lines.size(), 2u) << listen.out();
  std::map<std::string, nlohmann::json> by_robot;
  for (const auto& l : lines) {
    EXPECT_EQ(l.size(), 5u) << l.dump();  // exactly the documented keys
    for (const char* key : {"robot", "status", "T_global_robot", "fitness", "global_version"}) {
      EXPECT_TRUE(l.contains(key)) << key;
    }
    ASSERT_EQ(l["T_global_robot"].size(), 16u);
    by_robot[l["robot"]] = l;
  }
  ASSERT_TRUE(by_robot.count("r2"));
  const auto& t = by_robot["r2"]["T_global_robot"];
  EXPECT_NEAR(t[1].get<double>(), -1.0, 1e-12);  // 90 degrees about z, row-major
  EXPECT_NEAR(t[3].get<double>(), 4.0, 1e-12);
  EXPECT_NEAR(t[7].get<double>(), 5.0, 1e-12);
  EXPECT_EQ(by_robot["r2"]["status"], "aligned");
  ASSERT_TRUE(fs::exists(out));
  const auto saved = read_octree_file(out);
  EXPECT_EQ(saved->size(), tree->size());
  EXPECT_EQ(listen.err().find("Writing"), std::string::npos) << listen.err();
}

INSTANTIATE_TEST_SUITE_P(Vendors, CliListen, ::testing::Values("fastdds", "cyclone"));

TEST_F(Cli, ListenTimesOutWithExitCode3) {
  test::ChildProcess listen(kListen, {"--domain", domain(), "--until-aligned", "1", "--timeout", "1"},
                            test::Logs::split(log("listen")));
  EXPECT_EQ(listen.wait(kExit), 3) << listen.err();
  EXPECT_NE(listen.err().find("timeout"), std::string::npos) << listen.err();
}

TEST_F(Cli, RobotNotAlignedInTimeExitsWithCode3) {
  test::ChildProcess robot(kRobot,
                           {"--id", "r8", "--map", kData + "/geb079.bt", "--domain", domain(), "--exit-when-aligned",
                            "--timeout", "1"},
                           test::Logs::split(log("robot")));
  EXPECT_EQ(robot.wait(kExit), 3) << robot.err();
  EXPECT_NE(robot.err().find("not aligned"), std::string::npos) << robot.err();
}

TEST_F(Cli, RobotStopsCleanlyOnSigterm) {
  test::ChildProcess robot(kRobot, {"--id", "r9", "--map", kData + "/geb079.bt", "--domain", domain()},
                           test::Logs::split(log("robot")));
  std::this_thread::sleep_for(1500ms);
  ASSERT_TRUE(robot.running()) << robot.err();
  robot.signal(SIGTERM);
  EXPECT_EQ(robot.wait(kExit), 0) << robot.err();
  EXPECT_NE(robot.out().find("published update #1"), std::string::npos) << robot.out();
}

TEST_F(Cli, BadInputGivesExitCode2AndOneLine) {
  const auto run = [&](std::vector<std::string> args) {
    test::ChildProcess p(kRobot, args, test::Logs::split(log("bad")));
    const int code = p.wait(kExit);
    EXPECT_FALSE(p.err().empty());
    return code;
  };
  EXPECT_EQ(run({"--id", "9x", "--map", kData + "/geb079.bt"}), 2);
  EXPECT_EQ(run({"--id", "r1", "--map", kData + "/geb079.bt", "--profile", "nonsense"}), 2);
  EXPECT_EQ(run({"--id", "r1", "--map", kData + "/README.md"}), 2);
  EXPECT_EQ(run({"--id", "r1"}), 2);
  test::ChildProcess help(kListen, {"--help"}, test::Logs::split(log("help")));
  EXPECT_EQ(help.wait(kExit), 0);
  EXPECT_NE(help.out().find("--until-aligned"), std::string::npos);
}

}  // namespace
}  // namespace mapmerge
