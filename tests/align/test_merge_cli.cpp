// `mapmerge merge` end to end: exit codes, JSON output, clear errors for bad input.
#include <sys/wait.h>

#include <cstdio>
#include <filesystem>
#include <fstream>

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "mapmerge/map/crop.hpp"
#include "mapmerge/map/fusion.hpp"
#include "mapmerge/map/map_io.hpp"

namespace fs = std::filesystem;

namespace {

struct CliRun {
  int code = -1;
  std::string out;  ///< stdout and stderr
  std::string stdout_only;
};

CliRun run_cli(const std::string& args) {
  const std::string bin = std::string(MAPMERGE_BINARY_DIR) + "/bin/mapmerge";
  const fs::path err = fs::temp_directory_path() / ("mm_cli_err_" + std::to_string(::getpid()));
  CliRun r;
  FILE* pipe = ::popen((bin + " " + args + " 2>" + err.string()).c_str(), "r");
  if (pipe == nullptr) return r;
  char buf[4096];
  std::size_t n;
  while ((n = std::fread(buf, 1, sizeof buf, pipe)) > 0) r.stdout_only.append(buf, n);
  const int status = ::pclose(pipe);
  r.code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  std::ifstream e(err);
  r.out = r.stdout_only + std::string(std::istreambuf_iterator<char>(e), {});
  fs::remove(err);
  return r;
}

class MergeCli : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = fs::temp_directory_path() / ("mm_cli_" + std::to_string(::getpid()));
    fs::create_directories(dir_);
    const auto tree = mapmerge::read_octree_file(std::string(MAPMERGE_DATA_DIR) + "/fr_079.bt");
    using Box = Eigen::AlignedBox3d;
    const Box scene(Eigen::Vector3d(-10, -10, 0), Eigen::Vector3d(2, 10, 2));
    const Box model(Eigen::Vector3d(-2, -10, 0), Eigen::Vector3d(10, 10, 2));
    const Box far(Eigen::Vector3d(14, -10, 0), Eigen::Vector3d(26, 10, 2));
    T_R_ = mapmerge::paper_transform(12, 6, 0.5, 5, 5, 60);
    const Eigen::Isometry3d T_R(T_R_);
    mapmerge::write_octree_file(*mapmerge::crop_and_transform(*tree, scene, Eigen::Isometry3d::Identity()),
                                path("scene.bt"));
    mapmerge::write_octree_file(*mapmerge::crop_and_transform(*tree, model, T_R), path("model.ot"));
    mapmerge::write_octree_file(*mapmerge::crop_and_transform(*tree, far, T_R), path("far.bt"));
    std::ofstream(path("empty.bt")).close();
    std::ofstream(path("garbage.bt")) << "# Octomap OcTree binary file\nid OcTree\nres 0.05\ndata\n\x01\x02\x03";
    std::ofstream(path("map.txt")) << "not a map";
    std::ofstream(path("bad.yaml")) << "match: {methd: gcc}\n";
  }
  static void TearDownTestSuite() { fs::remove_all(dir_); }
  static std::string path(const std::string& name) { return (dir_ / name).string(); }
  static fs::path dir_;
  static Eigen::Matrix4d T_R_;
};
fs::path MergeCli::dir_;
Eigen::Matrix4d MergeCli::T_R_;

}  // namespace

TEST_F(MergeCli, AcceptedPairPrintsJsonAndWritesTheFusedMap) {
  const CliRun r = run_cli("merge " + path("scene.bt") + " " + path("model.ot") + " --json -o " + path("merged.bt"));
  ASSERT_EQ(r.code, 0) << r.out;
  const auto j = nlohmann::json::parse(r.stdout_only);
  EXPECT_TRUE(j.at("accepted").get<bool>());
  EXPECT_FALSE(j.at("rescued").get<bool>());  // the first search finds the paper's pair
  ASSERT_EQ(j.at("T_target_source").size(), 16U);
  Eigen::Matrix4d T;
  for (int i = 0; i < 16; ++i) T(i / 4, i % 4) = j["T_target_source"][i].get<double>();
  const Eigen::Matrix4d T_true = T_R_.inverse();
  EXPECT_LT((T.topRightCorner<3, 1>() - T_true.topRightCorner<3, 1>()).norm(), 0.1);
  EXPECT_GT(j.at("fitness").get<double>(), 0.0);
  EXPECT_GT(j.at("time_s").get<double>(), 0.0);
  EXPECT_TRUE(j.at("stages").contains("describe_ms"));
  // No octomap chatter on stdout: the JSON parsed above is all of it.
  const auto merged = mapmerge::read_octree_file(path("merged.bt"));
  const auto scene = mapmerge::read_octree_file(path("scene.bt"));
  using Box = Eigen::AlignedBox3d;
  const Box all(Eigen::Vector3d::Constant(-1e6), Eigen::Vector3d::Constant(1e6));
  EXPECT_GT(mapmerge::count_occupied(*merged, all), mapmerge::count_occupied(*scene, all) * 3 / 2);
}

/// Leaves of `a` whose occupancy `b` does not share at their centre (unknown in b counts).
std::size_t leaves_not_in(const octomap::OcTree& a, const octomap::OcTree& b) {
  std::size_t differ = 0;
  for (auto it = a.begin_leafs(), end = a.end_leafs(); it != end; ++it) {
    const octomap::OcTreeNode* n = b.search(it.getKey());
    if (n == nullptr || b.isNodeOccupied(n) != a.isNodeOccupied(*it)) ++differ;
  }
  return differ;
}

TEST_F(MergeCli, TheWrittenMapIsBothMapsFusedAtThePrintedTransform) {
  const CliRun r = run_cli("merge " + path("scene.bt") + " " + path("model.ot") + " --json -o " + path("fused.bt"));
  ASSERT_EQ(r.code, 0) << r.out;
  const auto j = nlohmann::json::parse(r.stdout_only);
  Eigen::Matrix4d T;
  for (int i = 0; i < 16; ++i) T(i / 4, i % 4) = j["T_target_source"][i].get<double>();
  // The reference: the model's evidence added to the scene's tree (stage 9, fuse_into).
  const auto reference = mapmerge::read_octree_file(path("scene.bt"));
  ASSERT_TRUE(mapmerge::fuse_into(*reference, *mapmerge::read_octree_file(path("model.ot")), T,
                                  mapmerge::FuseConfig{}).ok);
  const auto written = mapmerge::read_octree_file(path("fused.bt"));
  EXPECT_DOUBLE_EQ(written->getResolution(), reference->getResolution());
  EXPECT_GT(reference->getNumLeafNodes(), 100'000U);
  EXPECT_EQ(leaves_not_in(*reference, *written), 0U);
  EXPECT_EQ(leaves_not_in(*written, *reference), 0U);
  // `.ot`: the same map with its clamped log-odds.
  const CliRun ot = run_cli("merge " + path("scene.bt") + " " + path("model.ot") + " -o " + path("fused.ot"));
  ASSERT_EQ(ot.code, 0) << ot.out;
  const auto full = mapmerge::read_octree_file(path("fused.ot"));
  EXPECT_EQ(leaves_not_in(*reference, *full), 0U);
  EXPECT_EQ(leaves_not_in(*full, *reference), 0U);
  std::size_t between = 0;  // log-odds a fusion of evidence leaves strictly inside the clamps
  for (auto it = full->begin_leafs(), end = full->end_leafs(); it != end; ++it) {
    between += it->getLogOdds() < full->getClampingThresMaxLog() && it->getLogOdds() > full->getClampingThresMinLog();
  }
  EXPECT_GT(between, 0U);
}

TEST_F(MergeCli, NoOverlapExitsThreeAndWritesNothing) {
  const CliRun r = run_cli("merge " + path("scene.bt") + " " + path("far.bt") + " --json -o " + path("none.bt"));
  EXPECT_EQ(r.code, 3) << r.out;
  const auto j = nlohmann::json::parse(r.stdout_only);
  EXPECT_FALSE(j.at("accepted").get<bool>());
  EXPECT_TRUE(j.at("rescued").get<bool>());  // nothing fit: the denser second search ran and refused too
  EXPECT_FALSE(fs::exists(path("none.bt")));
}

TEST_F(MergeCli, BadInputsExitOneWithAClearMessage) {
  for (const std::string bad : {"empty.bt", "garbage.bt", "map.txt", "missing.bt"}) {
    const CliRun r = run_cli("merge " + path("scene.bt") + " " + path(bad));
    EXPECT_EQ(r.code, 1) << bad << ": " << r.out;
    EXPECT_NE(r.out.find(bad), std::string::npos) << "message does not name the file: " << r.out;
  }
}

TEST_F(MergeCli, BadUsageExitsTwo) {
  EXPECT_EQ(run_cli("merge " + path("scene.bt")).code, 2);
  EXPECT_EQ(run_cli("merge " + path("scene.bt") + " " + path("model.ot") + " --bogus").code, 2);
  const CliRun r = run_cli("merge " + path("scene.bt") + " " + path("model.ot") + " --config " + path("bad.yaml"));
  EXPECT_EQ(r.code, 2) << r.out;
  EXPECT_NE(r.out.find("match.methd"), std::string::npos) << r.out;
}
