// mapmerge-server: merges a robot fleet's OctoMaps into one global map over DDS.
//
// Exit codes: 0 clean shutdown (SIGINT/SIGTERM); 1 runtime failure (DDS entities, unexpected
// error); 2 bad command line or configuration; 3 the state store cannot be opened or read.

#include <malloc.h>
#include <unistd.h>

#include <atomic>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <iostream>
#include <thread>

#include <CLI/CLI.hpp>
#include <spdlog/spdlog.h>

#include "mapmerge/server/export.hpp"
#include "mapmerge/server/server.hpp"
#include "mapmerge/wire/fastdds.hpp"

namespace {

using mapmerge::server::ServerConfig;

enum ExitCode { kOk = 0, kRuntimeError = 1, kUsageError = 2, kStoreError = 3 };

constexpr int kMallocArenas = 2;  ///< glibc malloc arenas (see main)

struct Flags {
  std::string config_file, state_dir, profile, reference, discovery_server, keystore, enclave, log_level = "info";
  std::string export_prefix;
  int domain = -1;
  int threads = 0;
};

/// YAML first, then the flags given on the command line on top.
ServerConfig make_config(const Flags& f) {
  ServerConfig c = f.config_file.empty() ? ServerConfig{} : mapmerge::server::load_server_config(f.config_file);
  if (!f.state_dir.empty()) c.store.state_dir = f.state_dir;
  if (f.domain >= 0) c.network.domain = f.domain;
  if (!f.profile.empty()) c.network.profile = f.profile;
  if (!f.reference.empty()) c.merge.reference = f.reference;
  if (f.threads > 0) c.merge.threads = f.threads;
  if (!f.keystore.empty()) c.network.security_keystore = f.keystore;
  if (!f.enclave.empty()) c.network.security_enclave = f.enclave;
  if (!f.discovery_server.empty()) {
    c.network.discovery_server = f.discovery_server;
  } else if (const char* env = std::getenv("ROS_DISCOVERY_SERVER"); env && c.network.discovery_server.empty()) {
    c.network.discovery_server = env;
  }
  return c;
}

std::atomic<bool> g_stop_signal{false};

/// Runs only if SIGINT/SIGTERM reaches a thread that does not block them (one started before
/// main blocked them, or by a library that changed its mask): the process must still stop
/// cleanly, never die of the default action. Async-signal-safe: a flag and write(2).
extern "C" void on_stop_signal(int) {
  g_stop_signal = true;
  static const char kMsg[] = "mapmerge-server: stop signal taken by a thread that does not block it\n";
  const ssize_t ignored = ::write(STDERR_FILENO, kMsg, sizeof kMsg - 1);
  (void)ignored;
}

/// SIGINT/SIGTERM are blocked in every thread and waited for on one thread, which stops the
/// server; the handler above is the fallback (the wait also wakes every 100 ms to see its flag).
std::thread signal_thread(mapmerge::server::Server& server, sigset_t set) {
  return std::thread([&server, set] {
    const timespec period{0, 100'000'000};
    while (true) {
      const int sig = sigtimedwait(&set, nullptr, &period);
      if (sig == SIGUSR1) break;  // run() ended otherwise: nothing to stop
      if (sig > 0 || g_stop_signal) {
        spdlog::info("signal {} received", sig > 0 ? sig : SIGTERM);
        break;
      }
    }
    server.stop();
  });
}

int run_export(const ServerConfig& config, const std::string& prefix) {
  try {
    const auto e = mapmerge::server::export_global(config, prefix);
    std::cout << "global map " << e.version << ": " << prefix << ".bt, provenance of " << e.robots << " robots ("
              << e.owned_voxels << " voxels) in " << prefix << ".prov\n";
    return kOk;
  } catch (const mapmerge::server::StoreError& e) {
    std::cerr << "mapmerge-server: state store: " << e.what() << "\n";
    return kStoreError;
  } catch (const std::exception& e) {
    std::cerr << "mapmerge-server: " << e.what() << "\n";
    return kRuntimeError;
  }
}

}  // namespace

int main(int argc, char** argv) {
  // Maps are decoded, fused and freed on several threads: with glibc's default of up to 8
  // arenas per core, the memory each thread frees stays in its own arena and the resident set
  // grows with the number of threads that ever decoded a map. With two arenas, 2 fr_079 robots
  // peak at 435-510 MB instead of 620-680 MB, same latency (one arena: ~435 MB, but decoding
  // waits for the refinement threads' allocations). MALLOC_ARENA_MAX in the environment wins.
  if (std::getenv("MALLOC_ARENA_MAX") == nullptr) mallopt(M_ARENA_MAX, kMallocArenas);
  // A file size limit (RLIMIT_FSIZE) reached by the state store is a failed write (EFBIG),
  // reported and retried like a full disk, not the end of the process.
  std::signal(SIGXFSZ, SIG_IGN);
  sigset_t set;
  sigemptyset(&set);
  sigaddset(&set, SIGINT);
  sigaddset(&set, SIGTERM);
  sigaddset(&set, SIGUSR1);
  pthread_sigmask(SIG_BLOCK, &set, nullptr);  // before any thread starts: all inherit it
  struct sigaction stop_action {};
  stop_action.sa_handler = on_stop_signal;
  sigemptyset(&stop_action.sa_mask);
  stop_action.sa_flags = SA_RESTART;
  sigaction(SIGINT, &stop_action, nullptr);
  sigaction(SIGTERM, &stop_action, nullptr);
  CLI::App app{"mapmerge-server: merges a robot fleet's OctoMaps into one global map over DDS.\n"
               "Exit codes: 0 clean shutdown, 1 runtime error, 2 usage/config error, 3 state store error."};
  Flags f;
  app.add_option("--config", f.config_file, "YAML configuration file")->check(CLI::ExistingFile);
  app.add_option("--state-dir", f.state_dir, "directory of the persistent state (SQLite)");
  app.add_option("--domain", f.domain, "DDS domain id")->check(CLI::Range(0, 101));
  app.add_option("--profile", f.profile, "DDS profile: local, default or a Fast DDS XML file");
  app.add_option("--reference", f.reference, "robot whose map frame is the global frame (default: first heard)");
  app.add_option("--discovery-server", f.discovery_server,
                 "HOST:PORT of a Fast DDS discovery server (default: $ROS_DISCOVERY_SERVER)");
  app.add_option("--keystore", f.keystore,
                 "DDS Security keystore (scripts/make-keystore); default: ROS_SECURITY_KEYSTORE when "
                 "ROS_SECURITY_ENABLE=true, else security off");
  app.add_option("--enclave", f.enclave, "the server's enclave in the keystore (default: mapmerge_server)");
  app.add_option("--threads", f.threads, "merge threads (global searches, refinements, extra pairs)")->check(CLI::Range(1, 256));
  app.add_option("--log-level", f.log_level, "trace, debug, info, warn, error");
  app.add_option("--export-global", f.export_prefix,
                 "write the last global map of --state-dir as PREFIX.bt and its per-robot provenance as "
                 "PREFIX.prov (for `mapmerge render PREFIX.bt --by-robot PREFIX.prov`), then exit")
      ->needs("--state-dir");
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    app.exit(e);  // prints help or the error
    return e.get_exit_code() == 0 ? kOk : kUsageError;
  }

  // One write per log line: a server that is killed (or dies) leaves its log complete up to
  // its last line, also when stdout is a pipe or a file (fully buffered by default).
  std::setvbuf(stdout, nullptr, _IOLBF, 0);
  spdlog::set_pattern("%Y-%m-%dT%H:%M:%S.%e %^%l%$ %v");
  spdlog::set_level(spdlog::level::from_str(f.log_level));
  ServerConfig config;
  try {
    config = make_config(f);
    if (!config.network.security_keystore.empty()) {  // a missing or unreadable enclave is a configuration error
      (void)mapmerge::wire::SecurityOptions{config.network.security_keystore, config.network.security_enclave}.files();
    }
  } catch (const std::exception& e) {
    std::cerr << "mapmerge-server: " << e.what() << "\n";
    return kUsageError;
  }
  if (!f.export_prefix.empty()) return run_export(config, f.export_prefix);
  try {
    mapmerge::server::Server server(config);
    std::thread signals = signal_thread(server, set);
    server.run();
    pthread_kill(signals.native_handle(), SIGUSR1);  // wakes the signal thread if run() ended otherwise
    signals.join();
  } catch (const mapmerge::server::StoreError& e) {
    spdlog::error("state store: {}", e.what());
    return kStoreError;
  } catch (const mapmerge::wire::DdsError& e) {
    spdlog::error("DDS: {}", e.what());
    return kRuntimeError;
  } catch (const std::invalid_argument& e) {
    spdlog::error("configuration: {}", e.what());
    return kUsageError;
  } catch (const std::exception& e) {
    spdlog::error("{}", e.what());
    return kRuntimeError;
  }
  spdlog::info("stopped");
  return kOk;
}
