#pragma once
/// The vendor-free part of a client: serialisation, numbering, state, callbacks, threads.

#include <atomic>
#include <condition_variable>
#include <deque>
#include <map>
#include <mutex>
#include <optional>
#include <thread>

#include "mapmerge/client/client.hpp"
#include "transport.hpp"

namespace mapmerge::client::detail {

/// The DDS Security identity of `options` (explicit keystore, else ROS 2's environment, else off).
wire::SecurityOptions security_options(const Options& options);

/// This process's session id: 16 random hex digits, drawn once per process start.
const std::string& process_session_id();

/// Serialises a tree into a map update (no DDS). Throws MapError if compression fails.
MapMessage make_map_message(const octomap::OcTree& tree, const Options& options,
                            const std::string& session_id, std::uint64_t sequence_number);

/// Decodes and validates a received global map. Null (and `error` set) when rejected.
std::shared_ptr<const GlobalMap> decode_global_map(GlobalMapMessage&& message, std::size_t max_bytes,
                                                   std::string& error);

class ClientCore {
 public:
  ClientCore(Options options, Vendor vendor);
  ~ClientCore();

  PublishResult publish(const octomap::OcTree& tree);
  bool flush(std::chrono::milliseconds timeout);
  bool server_connected() const;
  bool wait_for_server(std::chrono::milliseconds timeout);
  void request_global_map();

  std::optional<Pose> pose(const std::string& robot_id) const;
  std::vector<Pose> poses() const;
  std::shared_ptr<const GlobalMap> global_map() const;

  void set_own_pose_callback(PoseCallback cb);
  void set_pose_callback(PoseCallback cb);
  void set_global_map_callback(GlobalMapCallback cb);
  void set_connection_callback(ConnectionCallback cb);
  void set_warning_callback(WarningCallback cb);

  const std::string& robot_id() const { return options_.robot_id; }
  const std::string& session_id() const { return options_.session_id; }
  Vendor vendor() const { return vendor_; }
  Statistics statistics() const;

 private:
  void on_pose(Pose&& pose);                       // DDS thread
  void on_global_map(GlobalMapMessage&& message);  // DDS thread
  void on_global_delta(GlobalDeltaMessage&& message);  // DDS thread
  void dispatch_loop();
  void deliver_poses(std::deque<Pose>& poses);      // dispatch thread
  void deliver_map(GlobalMapMessage&& message);     // dispatch thread
  void deliver_delta(GlobalDeltaMessage&& message);  // dispatch thread
  void report_write_failures();                     // dispatch thread
  void send_loop();
  void warn(const std::string& message);           // dispatch thread
  void check_connection();                         // dispatch thread
  void resend_last_map();                          // dispatch thread: the last written map again

  Options options_;
  Vendor vendor_;
  std::string requester_;

  // State, guarded by state_mutex_.
  mutable std::mutex state_mutex_;
  std::map<std::string, Pose> poses_;
  std::shared_ptr<const GlobalMap> global_map_;
  Statistics stats_;

  /// The callbacks. Set through the inbox (`pending`) and installed by the dispatch thread,
  /// which replays the current state to a new callback: every pose reaches it exactly once.
  struct Callbacks {
    std::optional<PoseCallback> own_pose, pose;
    std::optional<GlobalMapCallback> map;
    std::optional<ConnectionCallback> connection;
    std::optional<WarningCallback> warning;
  };
  void install_callbacks(Callbacks&& pending);  // dispatch thread
  Callbacks active_;                             // dispatch thread only

  // Dispatch thread inbox, guarded by inbox_mutex_.
  std::mutex inbox_mutex_;
  std::condition_variable inbox_cv_;
  std::deque<Pose> pose_inbox_;
  std::optional<GlobalMapMessage> map_inbox_;  // latest wins
  std::deque<GlobalDeltaMessage> delta_inbox_;  // in arrival order, the oldest dropped beyond a few
  bool request_pending_ = false;
  Callbacks pending_;
  bool callbacks_pending_ = false;
  bool was_connected_ = false;                  // dispatch thread only
  bool ask_on_connect_ = false;                 // dispatch thread only: a request waits for its reader
  std::uint64_t failures_reported_ = 0;         // dispatch thread only
  std::optional<std::pair<std::uint64_t, std::uint64_t>> last_map_;  // version, payload hash of the map held; dispatch thread
  std::chrono::steady_clock::time_point last_failure_warning_;  // dispatch thread only

  // Send thread outbox, guarded by send_mutex_.
  std::mutex send_mutex_;
  std::condition_variable send_cv_;
  std::optional<MapMessage> outbox_;  // latest wins
  std::optional<MapMessage> written_;  // the last map written: sent again to a server that (re)appears
  bool outbox_resend_ = false;         // the outbox holds written_ again (not counted in the statistics)
  bool sending_ = false;
  std::uint64_t next_sequence_ = 1;

  std::atomic<bool> stop_{false};
  std::atomic<std::uint64_t> nonce_{0};
  std::unique_ptr<Transport> transport_;  // after the state it calls into
  std::thread dispatch_thread_;
  std::thread send_thread_;
};

}  // namespace mapmerge::client::detail
