#pragma once
/// mapmerge-server as one application object (run()/stop()): restores the registry from the
/// store, wires DDS input to the scheduler and pipeline, and publishes the global map, poses,
/// tf and status from its main loop (rate-limited, periodically republished, on request).

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <memory>
#include <mutex>
#include <optional>
#include <vector>

#include "mapmerge/server/config.hpp"
#include "mapmerge/server/dds_io.hpp"
#include "mapmerge/server/global_map.hpp"
#include "mapmerge/server/pipeline.hpp"
#include "mapmerge/server/registry.hpp"
#include "mapmerge/server/scheduler.hpp"
#include "mapmerge/server/store.hpp"

namespace mapmerge::server {

class Server {
 public:
  /// Opens the store (StoreError), restores it, creates the DDS entities (wire::DdsError) and
  /// publishes the restored global map and poses.
  explicit Server(ServerConfig config);
  ~Server();
  Server(const Server&) = delete;
  Server& operator=(const Server&) = delete;

  /// Serves until stop(). Returns after the workers have finished.
  void run();
  /// Asks run() to return; safe from any thread (not from a signal handler).
  void stop();

 private:
  using Clock = std::chrono::steady_clock;
  void restore();
  /// Whether the last global map holds exactly the registry's aligned robots' current maps.
  bool global_is_current() const;
  void on_map(MapSample sample);
  /// A robot's map writers came or went (DDS discovery): status, log, and with
  /// merge.keep_lost_maps false a new global map without (or again with) it.
  void on_presence(const std::string& robot, bool alive);
  void loop_once();
  void publish_global();
  void republish();
  void publish_status();
  std::vector<PoseOut> current_poses() const;

  ServerConfig config_;
  Registry registry_;
  GlobalMapBuilder builder_{config_};
  std::unique_ptr<Store> store_;
  std::unique_ptr<Pipeline> pipeline_;
  std::unique_ptr<Scheduler> scheduler_;
  std::unique_ptr<DdsIo> dds_;

  std::mutex mutex_;
  std::condition_variable cv_;
  std::atomic<bool> stopping_{false};
  std::atomic<bool> dirty_{false};
  bool trim_due_ = false;  ///< maps were freed since the heap was last trimmed (main loop only)
  std::atomic<bool> requested_{false};
  std::atomic<std::uint64_t> received_{0};
  std::atomic<std::uint64_t> ignored_{0};      ///< duplicate and out-of-order updates
  std::atomic<std::uint64_t> conflicting_{0};  ///< updates of a session that another one replaced
  std::uint64_t version_ = 0;
  std::optional<GlobalMapOut> last_global_;
  Clock::time_point last_build_{}, last_republish_{}, last_status_{}, last_store_retry_{};
};

}  // namespace mapmerge::server
