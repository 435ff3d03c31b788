// `mapmerge scenario` + `mapmerge report`: the demo's verdict is computed from the truth, and a
// pose that is off is reported as such.

#include <cstdio>
#include <cstdlib>
#include <sys/wait.h>
#include <unistd.h>
#include <filesystem>
#include <fstream>
#include <string>

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include <Eigen/Geometry>

namespace {

namespace fs = std::filesystem;

int run(const std::string& command, std::string* output = nullptr) {
  std::string text;
  FILE* pipe = ::popen((command + " 2>&1").c_str(), "r");
  if (pipe == nullptr) return -1;
  char buf[4096];
  while (std::fgets(buf, sizeof buf, pipe) != nullptr) text += buf;
  const int status = ::pclose(pipe);
  if (output != nullptr) *output = text;
  return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
}

class Report : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() / ("mapmerge_report_" + std::to_string(::getpid()));
    fs::create_directories(dir_);
    const std::string cmd = std::string(MAPMERGE_CLI) + " scenario " + MAPMERGE_DATA_DIR +
                            "/geb079.bt -o " + dir_.string() + " --robots 3 --seed 5";
    ASSERT_EQ(run(cmd), 0);
    std::ifstream in(dir_ / "truth.json");
    truth_ = nlohmann::json::parse(in);
  }
  void TearDown() override { fs::remove_all(dir_); }

  /// Writes one aligned pose line per robot, the i-th pose given by `pose(i, truth)`.
  template <class F>
  std::string write_poses(F&& pose) {
    const fs::path path = dir_ / "poses.jsonl";
    std::ofstream out(path);
    int i = 0;
    for (const auto& r : truth_.at("robots")) {
      nlohmann::json line;
      line["robot"] = r.at("id");
      line["status"] = "aligned";
      line["T_global_robot"] = pose(i++, r.at("T_global_robot").get<std::vector<double>>());
      line["fitness"] = 0.01;
      line["global_version"] = 3;
      out << "1700000000.5 " << line.dump() << "\n";
    }
    return path.string();
  }

  std::string report(const std::string& poses) {
    return std::string(MAPMERGE_CLI) + " report --truth " + (dir_ / "truth.json").string() + " --poses " + poses;
  }

  fs::path dir_;
  nlohmann::json truth_;
};

TEST_F(Report, ScenarioWritesOneMapPerRobotWithItsTruth) {
  ASSERT_EQ(truth_.at("robots").size(), 3u);
  for (const auto& r : truth_.at("robots")) {
    EXPECT_TRUE(fs::exists(dir_ / (r.at("id").get<std::string>() + ".bt")));
    EXPECT_GT(r.at("occupied_leaves").get<int>(), 1000);
  }
  // The reference robot's frame is the global frame.
  const auto T0 = truth_.at("robots")[0].at("T_global_robot").get<std::vector<double>>();
  for (int i = 0; i < 16; ++i) EXPECT_NEAR(T0[static_cast<std::size_t>(i)], (i % 5 == 0) ? 1.0 : 0.0, 1e-9);
}

TEST_F(Report, TruePosesPass) {
  std::string out;
  const auto poses = write_poses([](int, std::vector<double> T) { return T; });
  EXPECT_EQ(run(report(poses), &out), 0) << out;
  EXPECT_NE(out.find("PASS: 3 of 3"), std::string::npos) << out;
}

TEST_F(Report, ARotatedPoseFails) {
  std::string out;
  const auto poses = write_poses([](int i, std::vector<double> T) {
    if (i != 2) return T;
    Eigen::Matrix4d M;
    for (int k = 0; k < 16; ++k) M(k / 4, k % 4) = T[static_cast<std::size_t>(k)];
    Eigen::Matrix4d turn = Eigen::Matrix4d::Identity();
    turn.block<3, 3>(0, 0) = Eigen::AngleAxisd(5.0 * M_PI / 180.0, Eigen::Vector3d::UnitZ()).toRotationMatrix();
    M = M * turn;
    for (int k = 0; k < 16; ++k) T[static_cast<std::size_t>(k)] = M(k / 4, k % 4);
    return T;
  });
  EXPECT_EQ(run(report(poses), &out), 3) << out;
  EXPECT_NE(out.find("FAIL: 2 of 3"), std::string::npos) << out;
  EXPECT_NE(out.find("out of tolerance"), std::string::npos) << out;
}

TEST_F(Report, AShiftedPoseFails) {
  std::string out;
  const auto poses = write_poses([](int i, std::vector<double> T) {
    if (i == 1) T[3] += 0.5;  // half a metre along x
    return T;
  });
  EXPECT_EQ(run(report(poses), &out), 3) << out;
  EXPECT_NE(out.find("FAIL: 2 of 3"), std::string::npos) << out;
}

TEST_F(Report, AMissingRobotFails) {
  std::string out;
  const fs::path path = dir_ / "poses.jsonl";
  std::ofstream(path) << "{\"robot\": \"r1\", \"status\": \"aligned\", \"T_global_robot\": "
                         "[1,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1], \"fitness\": 0}\n"
                         "{\"robot\": \"r2\", \"status\": \"unknown\", \"T_global_robot\": "
                         "[1,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1], \"fitness\": 0}\n";
  EXPECT_EQ(run(report(path.string()), &out), 3) << out;
  EXPECT_NE(out.find("FAIL: 1 of 3"), std::string::npos) << out;
}

}  // namespace
