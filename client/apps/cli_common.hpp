#pragma once
/// What mapmerge-robot and mapmerge-listen share: DDS flags, quiet and flushed output, signals,
/// exit codes, the JSON form of a pose.

#include <atomic>
#include <chrono>
#include <string>

#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>

#include "mapmerge/client/client.hpp"

namespace mapmerge::cli {

/// Exit codes of both CLIs (documented in their --help).
enum ExitCode : int {
  kExitOk = 0,        ///< done (or stopped by SIGINT/SIGTERM)
  kExitFailure = 1,   ///< runtime failure: DDS entities, writing a file
  kExitUsage = 2,     ///< bad flags or unreadable input
  kExitTimeout = 3,   ///< --timeout reached before the goal
  kExitNoMap = 4,     ///< mapmerge-listen: goal reached but no global map to save for -o
};

/// The DDS flags every program takes.
struct DdsFlags {
  int domain = 0;
  std::string profile = "local";
  std::string discovery_server;
  std::string vendor = "fastdds";
  std::string keystore;
  std::string enclave;
  bool verbose = false;
};
void add_dds_flags(CLI::App& app, DdsFlags& flags);
/// Why the flags (and the options made of them) cannot work; empty when they can.
std::string check_flags(const DdsFlags& flags, const client::Options& options);
/// Client options from the flags (robot id left to the caller).
client::Options client_options(const DdsFlags& flags);

/// Keeps stdout for the program's own lines (each flushed) and hides the libraries' stderr
/// chatter (OctoMap's "Writing N nodes") unless verbose: fd 2 goes to /dev/null and the
/// program's errors go to the original stderr through err().
void setup_output(bool verbose);
void out(const std::string& line);  ///< one line on stdout, flushed
void err(const std::string& line);  ///< one line on the original stderr, flushed

/// SIGINT/SIGTERM set the stop flag (installed once).
void install_signal_handlers();
bool stop_requested();

/// Sleeps up to `d`, returning early when a stop was requested.
void sleep_interruptible(std::chrono::milliseconds d);

/// {"robot","status","T_global_robot":[16 row-major],"fitness","global_version"}
nlohmann::json pose_json(const client::Pose& pose);
/// "aligned  t=(x, y, z) m  yaw=.. deg  fitness=.. m  global v7"
std::string pose_text(const client::Pose& pose);

/// Parses argv; returns an exit code when the program must stop (help: 0, error: kExitUsage).
bool parse(CLI::App& app, int argc, char** argv, int& exit_code);

}  // namespace mapmerge::cli
