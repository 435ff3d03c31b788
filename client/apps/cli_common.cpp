#include "cli_common.hpp"

#include <cmath>
#include <csignal>
#include <cstdio>
#include <iomanip>
#include <iostream>
#include <sstream>
#include <thread>

#include <fcntl.h>
#include <unistd.h>

namespace mapmerge::cli {
namespace {

std::atomic<bool> g_stop{false};
FILE* g_err = stderr;

void on_signal(int) { g_stop = true; }

}  // namespace

void add_dds_flags(CLI::App& app, DdsFlags& flags) {
  app.add_option("--domain", flags.domain, "DDS domain id")->check(CLI::Range(0, 232))->capture_default_str();
  app.add_option("--profile", flags.profile, "network profile: local (127.0.0.1 only), default, or FILE.xml")
      ->capture_default_str();
  app.add_option("--discovery-server", flags.discovery_server,
                 "Fast DDS discovery server HOST:PORT (else ROS_DISCOVERY_SERVER, else simple discovery)");
  app.add_option("--vendor", flags.vendor, "DDS implementation of this program")
      ->check(CLI::IsMember({"fastdds", "cyclone"}))
      ->capture_default_str();
  app.add_option("--keystore", flags.keystore,
                 "DDS Security keystore (scripts/make-keystore); default: ROS_SECURITY_KEYSTORE when "
                 "ROS_SECURITY_ENABLE=true, else security off");
  app.add_option("--enclave", flags.enclave, "enclave in the keystore (default: the robot id)");
  app.add_flag("-v,--verbose", flags.verbose, "show the DDS and OctoMap libraries' own messages on stderr");
}

std::string check_flags(const DdsFlags& flags, const client::Options& options) {
  if (flags.vendor == "cyclone" && !flags.discovery_server.empty()) {
    return "--discovery-server needs --vendor fastdds (Cyclone DDS has no Fast DDS discovery server client)";
  }
  return client::check_options(options);
}

client::Options client_options(const DdsFlags& flags) {
  client::Options o;
  o.domain = flags.domain;
  o.profile = flags.profile;
  o.discovery_server = flags.discovery_server;
  o.keystore = flags.keystore;
  o.enclave = flags.enclave;
  return o;
}

void setup_output(bool verbose) {
  std::ios::sync_with_stdio(true);
  std::setvbuf(stdout, nullptr, _IOLBF, 0);
  client::route_dds_logs_to_stderr();
  if (verbose) return;
  const int saved = ::dup(STDERR_FILENO);
  const int null = ::open("/dev/null", O_WRONLY);
  if (saved < 0 || null < 0) return;
  FILE* f = ::fdopen(saved, "w");
  if (f == nullptr) return;
  std::fflush(stderr);
  ::dup2(null, STDERR_FILENO);
  ::close(null);
  g_err = f;
}

void out(const std::string& line) {
  std::fputs(line.c_str(), stdout);
  std::fputc('\n', stdout);
  std::fflush(stdout);
}

void err(const std::string& line) {
  std::fputs(line.c_str(), g_err);
  std::fputc('\n', g_err);
  std::fflush(g_err);
}

void install_signal_handlers() {
  struct sigaction sa {};
  sa.sa_handler = on_signal;
  sigemptyset(&sa.sa_mask);
  sigaction(SIGINT, &sa, nullptr);
  sigaction(SIGTERM, &sa, nullptr);
  std::signal(SIGPIPE, SIG_IGN);
}

bool stop_requested() { return g_stop; }

void sleep_interruptible(std::chrono::milliseconds d) {
  const auto deadline = std::chrono::steady_clock::now() + d;
  while (!g_stop && std::chrono::steady_clock::now() < deadline) {
    const auto left = deadline - std::chrono::steady_clock::now();
    std::this_thread::sleep_for(std::min<std::chrono::steady_clock::duration>(left, std::chrono::milliseconds(20)));
  }
}

nlohmann::json pose_json(const client::Pose& pose) {
  const auto m = pose.matrix();
  return nlohmann::json{{"robot", pose.robot_id},
                        {"status", client::to_string(pose.status)},
                        {"T_global_robot", std::vector<double>(m.begin(), m.end())},
                        {"fitness", pose.fitness},
                        {"global_version", pose.global_version}};
}

std::string pose_text(const client::Pose& pose) {
  const auto m = pose.matrix();
  const double yaw_deg = std::atan2(m[4], m[0]) * 180.0 / M_PI;
  std::ostringstream ss;
  ss << std::fixed << std::setprecision(3) << std::left << std::setw(8) << client::to_string(pose.status)
     << " t=(" << pose.translation[0] << ", " << pose.translation[1] << ", " << pose.translation[2] << ") m"
     << std::setprecision(2) << "  yaw=" << yaw_deg << " deg" << std::setprecision(4)
     << "  fitness=" << pose.fitness << " m  global v" << pose.global_version;
  return ss.str();
}

bool parse(CLI::App& app, int argc, char** argv, int& exit_code) {
  try {
    app.parse(argc, argv);
    return true;
  } catch (const CLI::CallForHelp& e) {
    exit_code = app.exit(e);
  } catch (const CLI::CallForAllHelp& e) {
    exit_code = app.exit(e);
  } catch (const CLI::ParseError& e) {
    std::cerr << app.get_name() << ": " << e.what() << " (see --help)" << std::endl;
    exit_code = kExitUsage;
  }
  return false;
}

}  // namespace mapmerge::cli
