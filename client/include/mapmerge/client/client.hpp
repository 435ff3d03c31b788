#pragma once
/// mapmerge's robot-side library: publish a robot's OctoMap to the mapmerge server and receive
/// the robot's pose in the global frame, the other robots' poses and the global map.
///
///   mapmerge::client::Options options;
///   options.robot_id = "r1";
///   mapmerge::Client client(options);              // Fast DDS (mapmerge::CycloneClient: Cyclone)
///   client.on_own_pose([](const mapmerge::client::Pose& p) { ... });
///   client.publish(tree);                          // any time the local map changed
///
/// No DDS vendor type appears in this header (the transports live behind a pimpl).
///
/// Threading: every method may be called from any thread. Callbacks run on one thread owned by
/// the client, one at a time, never on a DDS thread; a slow callback delays later callbacks of
/// this client only. Only wait_for_server() and flush() wait on the network, at most the time
/// they are given; publish() hands its update to a sending thread whose DDS writes block at
/// most Options::max_block (the destructor waits for at most one such write).

#include <array>
#include <chrono>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>
#include <string_view>
#include <vector>

namespace octomap {
class OcTree;
}

namespace mapmerge {
namespace client {

/// Thrown by a client's constructor for bad options or a DDS entity that cannot be created.
class ClientError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

/// The DDS implementation a client speaks through (both interoperate on the wire).
enum class Vendor { kFastdds, kCyclone };
const char* to_string(Vendor vendor);                     ///< "fastdds" / "cyclone"
std::optional<Vendor> parse_vendor(std::string_view name);  ///< inverse of to_string()

/// Alignment state of a robot's map in the global frame (mapmerge::PoseStatus on the wire).
enum class PoseStatus { kUnknown, kAligned, kRejected };
const char* to_string(PoseStatus status);  ///< "unknown" / "aligned" / "rejected"

/// Where a robot's map frame lies in the global frame, as published by the server.
struct Pose {
  std::string robot_id;
  PoseStatus status = PoseStatus::kUnknown;
  std::array<double, 3> translation{0.0, 0.0, 0.0};    ///< of T_global_robot [m]
  std::array<double, 4> rotation{0.0, 0.0, 0.0, 1.0};  ///< of T_global_robot, unit quaternion x, y, z, w
  double fitness = 0.0;             ///< mean inlier distance of the supporting alignment [m]
  double quality = 0.0;             ///< confidence of the pose, 0..1
  std::uint64_t global_version = 0; ///< the global map version this pose belongs to
  std::string global_frame_id;      ///< e.g. "global"
  std::string robot_frame_id;       ///< e.g. "r1/map"
  double stamp = 0.0;               ///< server time of the pose [s since the Unix epoch]

  /// T_global_robot as a 4x4 homogeneous matrix, row-major (the quaternion is normalised).
  std::array<double, 16> matrix() const;
};

/// One robot map that went into a global map.
struct Contribution {
  std::string robot_id;
  std::string session_id;
  std::uint64_t sequence_number = 0;
};

/// The server's fused map of every aligned robot, in the global frame.
struct GlobalMap {
  std::uint64_t version = 0;        ///< increases with every change
  std::string frame_id;             ///< the global frame
  double resolution = 0.0;          ///< [m]
  double stamp = 0.0;               ///< [s since the Unix epoch]
  std::string encoding;             ///< wire encoding it arrived in ("octomap-bt", ...)
  std::size_t payload_bytes = 0;    ///< size on the wire [bytes]
  std::vector<Contribution> contributors;
  /// The decoded, validated map (never null). A new version usually comes as the blocks that
  /// changed: while nobody but the client holds the latest GlobalMap and its tree, the client
  /// patches that tree in place (O(change), where decoding a whole Freiburg-size map takes
  /// ~100 ms), so the `tree` of a new version may be the same object as the last one's. Keep a
  /// GlobalMap (or its tree) only as long as you read it: while one is held, each new version is
  /// decoded whole instead. Do not read a tree through a weak_ptr.
  std::shared_ptr<const octomap::OcTree> tree;
};

/// Construction settings of a client. Plain values; the CLIs fill them from flags.
struct Options {
  std::string robot_id;         ///< this robot's id (a ROS 2 name token); empty: observe only
  int domain = 0;               ///< DDS domain id (0..101 on hosts with the default port range)
  std::string profile = "local";  ///< "local" (127.0.0.1 only), "default" (a real fleet) or FILE.xml
  std::string discovery_server;   ///< Fast DDS discovery server "HOST:PORT"; empty:
                                  ///< ROS_DISCOVERY_SERVER if set, else simple discovery
  std::string keystore;         ///< DDS Security keystore (scripts/make-keystore, SROS2 layout);
                                ///< empty: ROS_SECURITY_KEYSTORE if ROS_SECURITY_ENABLE=true, else off
  std::string enclave;          ///< enclave in the keystore; empty: ROS_SECURITY_ENCLAVE, else the robot id
  std::string frame_id;         ///< the robot's map frame; empty: "<robot_id>/map"
  std::string session_id;       ///< empty: this process's random session id (new per start)
  bool zstd = false;            ///< compress map updates ("octomap-bt+zstd") instead of "octomap-bt"
  int zstd_level = 3;           ///< zstd level when compressing (1 fast .. 19 small)
  std::chrono::milliseconds max_block{200};  ///< longest one DDS write may block the client's
                                             ///< sending thread, which also bounds the destructor [ms]
  bool receive_global_map = true;   ///< subscribe to the (large) global map
  std::size_t max_global_map_bytes = 100'000'000;  ///< larger global maps are rejected [bytes]
  std::chrono::milliseconds poll_period{100};      ///< server-presence check period [ms]
};

/// Why `options` cannot make a client (bad robot id, domain, profile, zstd level); empty when
/// they can. Constructors throw ClientError with this message; CLIs check first.
std::string check_options(const Options& options);

/// What publish() did.
struct PublishResult {
  bool queued = false;               ///< handed to the sending thread
  std::uint64_t sequence_number = 0; ///< number of this update within the session
  std::size_t bytes = 0;             ///< payload size on the wire [bytes]
  std::string encoding;              ///< "octomap-bt" or "octomap-bt+zstd"
  std::string error;                 ///< why it was not queued; empty when queued
};

/// Counters of a client since construction.
struct Statistics {
  std::uint64_t updates_published = 0;  ///< map updates handed to DDS
  std::uint64_t updates_coalesced = 0;  ///< updates replaced by a newer one before sending
  std::uint64_t write_failures = 0;     ///< DDS writes that failed (e.g. timed out)
  std::uint64_t poses_received = 0;
  std::uint64_t global_maps_received = 0;
  std::uint64_t global_maps_rejected = 0;  ///< failed validation (reason via on_warning)
  std::uint64_t global_maps_patched = 0;   ///< of global_maps_received: patched from the changed blocks
  std::uint64_t global_deltas_rejected = 0;  ///< changed blocks that failed validation (the map is decoded whole)
};

using PoseCallback = std::function<void(const Pose&)>;
using GlobalMapCallback = std::function<void(const std::shared_ptr<const GlobalMap>&)>;
using ConnectionCallback = std::function<void(bool connected)>;
using WarningCallback = std::function<void(const std::string& message)>;

/// Sends the DDS vendors' own log lines to stderr (Fast DDS prints on stdout by default), for
/// programs whose stdout is read by machines.
void route_dds_logs_to_stderr();

namespace detail {
class ClientCore;
}  // namespace detail

}  // namespace client

/// A robot's connection to the mapmerge server over Fast DDS. Construction joins the DDS
/// domain and never waits for the server; a server that appears later, disappears or restarts
/// is handled (the client keeps its last pose and map and carries on).
class Client {
 public:
  /// Fast DDS. Throws client::ClientError for a bad robot id or profile, or a DDS failure.
  explicit Client(client::Options options);
  virtual ~Client();
  Client(const Client&) = delete;
  Client& operator=(const Client&) = delete;

  /// Serialises `tree` (OctoMap binary, optionally zstd), stamps and numbers it and hands it to
  /// the sending thread. Costs one serialisation of the tree on the caller's thread and never
  /// waits on the network; an update not yet sent is replaced by a newer one (latest wins).
  client::PublishResult publish(const octomap::OcTree& tree);
  /// Waits until every queued update is written and acknowledged by the matched readers, at
  /// most `timeout`. True when all were.
  bool flush(std::chrono::milliseconds timeout);

  /// True once a server is matched (it publishes poses or the global map to us).
  bool server_connected() const;
  /// Waits at most `timeout` for a server. True when connected.
  bool wait_for_server(std::chrono::milliseconds timeout);
  /// Asks the server to publish the global map and the poses again (never blocks).
  void request_global_map();

  /// This robot's latest pose, if the server published one.
  std::optional<client::Pose> own_pose() const;
  /// The latest pose of `robot_id`, if any.
  std::optional<client::Pose> pose(const std::string& robot_id) const;
  /// The latest pose of every robot heard of (this one included), sorted by robot id.
  std::vector<client::Pose> poses() const;
  /// The latest global map, or null before the first one.
  std::shared_ptr<const client::GlobalMap> global_map() const;

  /// Callbacks (replace any earlier one; pass nullptr to remove). A new callback first gets
  /// the current state (the poses, the global map, `true` if connected), then every change:
  /// each received pose reaches it exactly once. Do not destroy the client from a callback.
  void on_own_pose(client::PoseCallback callback);
  void on_pose(client::PoseCallback callback);  ///< every robot's poses, this one included
  void on_global_map(client::GlobalMapCallback callback);
  void on_server_connection(client::ConnectionCallback callback);
  void on_warning(client::WarningCallback callback);  ///< rejected payloads, failed writes

  const std::string& robot_id() const;
  const std::string& session_id() const;
  client::Vendor vendor() const;
  client::Statistics statistics() const;

 protected:
  Client(client::Options options, client::Vendor vendor);

 private:
  std::unique_ptr<client::detail::ClientCore> core_;
};

/// The same client over Cyclone DDS (C API): proves a Cyclone-based robot stack, ROS 2's
/// default vendor on many distributions, talks to the Fast DDS server. Options::discovery_server
/// is not supported (Cyclone has no Fast DDS discovery server client). With DDS Security, all
/// Cyclone clients of one process and domain must use the same identity (Cyclone DDS 0.10
/// applies the first participant's).
class CycloneClient : public Client {
 public:
  explicit CycloneClient(client::Options options);
};

/// A client of the given vendor.
std::unique_ptr<Client> make_client(client::Options options, client::Vendor vendor);

}  // namespace mapmerge
