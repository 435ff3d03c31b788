// `mapmerge report`: estimated against true robot poses, as a table (the demo's verdict).

#include <cmath>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <map>
#include <sstream>

#include <nlohmann/json.hpp>

#include "commands.hpp"
#include "scenario.hpp"

namespace mapmerge::app {
namespace {

struct ReportOptions {
  std::string truth;
  std::string poses;
  double start_time = 0.0;       ///< epoch seconds when the robots started (0: no timing column)
  double max_rotation_deg = 2.0; ///< tolerance on the rotation error [deg]
  double max_translation = 0.3;  ///< tolerance on the translation error [m]
};

struct Estimate {
  nlohmann::json pose;
  double first_aligned = -1.0;  ///< epoch seconds of the first aligned pose, -1 if none
};

/// Reads `[epoch] {json}` lines; keeps the last pose of each robot and its first aligned time.
std::map<std::string, Estimate> read_poses(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw std::runtime_error("cannot read poses '" + path + "'");
  std::map<std::string, Estimate> out;
  std::string line;
  while (std::getline(in, line)) {
    const auto brace = line.find('{');
    if (brace == std::string::npos) continue;
    const double stamp = brace > 0 ? std::atof(line.substr(0, brace).c_str()) : 0.0;
    const auto j = nlohmann::json::parse(line.substr(brace), nullptr, /*allow_exceptions=*/false);
    if (j.is_discarded() || !j.contains("robot")) continue;
    auto& e = out[j.at("robot").get<std::string>()];
    e.pose = j;
    if (j.value("status", "") == "aligned" && e.first_aligned < 0.0) e.first_aligned = stamp;
  }
  return out;
}

std::string pose_text(const Eigen::Matrix4d& T) {
  const Eigen::Vector3d t = T.block<3, 1>(0, 3);
  const double yaw = std::atan2(T(1, 0), T(0, 0)) * 180.0 / M_PI;
  char buf[64];
  std::snprintf(buf, sizeof buf, "(%6.2f %6.2f %5.2f | %6.1f°)", t.x(), t.y(), t.z(), yaw);
  return buf;
}

int run(const ReportOptions& o) {
  std::ifstream tin(o.truth);
  if (!tin) throw std::runtime_error("cannot read truth '" + o.truth + "'");
  const auto truth = nlohmann::json::parse(tin);
  const auto estimates = read_poses(o.poses);
  std::printf("%-6s %-30s %-30s %9s %9s %9s %8s\n", "robot", "true pose (x y z | yaw)",
              "estimated pose", "rot [deg]", "trans [m]", "fitness", "t [s]");
  int failures = 0;
  for (const auto& r : truth.at("robots")) {
    const std::string id = r.at("id");
    const Eigen::Matrix4d T_true = from_row_major(r.at("T_global_robot").get<std::vector<double>>());
    const auto it = estimates.find(id);
    if (it == estimates.end() || it->second.pose.value("status", "") != "aligned") {
      std::printf("%-6s %-30s %-30s\n", id.c_str(), pose_text(T_true).c_str(),
                  it == estimates.end() ? "(no pose)" : it->second.pose.value("status", "?").c_str());
      ++failures;
      continue;
    }
    const auto& p = it->second.pose;
    const Eigen::Matrix4d T_est = from_row_major(p.at("T_global_robot").get<std::vector<double>>());
    const PoseError e = pose_error(T_true, T_est);
    const bool ok = e.rotation_deg <= o.max_rotation_deg && e.translation_m <= o.max_translation;
    failures += ok ? 0 : 1;
    const double t = o.start_time > 0 && it->second.first_aligned > 0 ? it->second.first_aligned - o.start_time : NAN;
    std::printf("%-6s %-30s %-30s %9.3f %9.3f %9.4f %8.1f%s\n", id.c_str(), pose_text(T_true).c_str(),
                pose_text(T_est).c_str(), e.rotation_deg, e.translation_m, p.value("fitness", NAN), t,
                ok ? "" : "  <- out of tolerance");
  }
  std::printf("%s: %d of %zu robots within %.1f° and %.2f m\n", failures == 0 ? "PASS" : "FAIL",
              static_cast<int>(truth.at("robots").size()) - failures, truth.at("robots").size(),
              o.max_rotation_deg, o.max_translation);
  return failures == 0 ? 0 : 3;
}

}  // namespace

void add_report_command(CLI::App& app, int& exit_code) {
  auto options = std::make_shared<ReportOptions>();
  auto* cmd = app.add_subcommand("report", "compare estimated robot poses with the truth of a scenario");
  cmd->add_option("--truth", options->truth, "truth.json written by `mapmerge scenario`")->required()->check(CLI::ExistingFile);
  cmd->add_option("--poses", options->poses, "pose lines of `mapmerge-listen --json`, optionally prefixed by epoch seconds")
      ->required()->check(CLI::ExistingFile);
  cmd->add_option("--start", options->start_time, "epoch seconds when the robots started");
  cmd->add_option("--max-rot", options->max_rotation_deg, "rotation tolerance [deg]");
  cmd->add_option("--max-trans", options->max_translation, "translation tolerance [m]");
  cmd->callback([options, &exit_code] { exit_code = run(*options); });
}

}  // namespace mapmerge::app
