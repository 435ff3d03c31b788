#pragma once
/// The vendor side of a client: one implementation per DDS vendor moves vendor-neutral
/// messages on mapmerge's topics. Everything above it (client_core.cpp) is vendor-free.

#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "mapmerge/client/client.hpp"
#include "mapmerge/map/global_delta.hpp"
#include "mapmerge/wire/profile.hpp"
#include "mapmerge/wire/security.hpp"

namespace mapmerge::client::detail {

/// mapmerge::MapUpdate without vendor types.
struct MapMessage {
  std::string robot_id;
  std::string session_id;
  std::uint64_t sequence_number = 0;
  std::int32_t stamp_sec = 0;
  std::uint32_t stamp_nanosec = 0;
  std::string frame_id;
  double resolution = 0.0;
  std::string encoding;
  std::vector<std::uint8_t> data;
};

/// mapmerge::GlobalMap without vendor types, the payload not yet decoded.
struct GlobalMapMessage {
  std::uint64_t version = 0;
  double stamp = 0.0;
  std::string frame_id;
  double resolution = 0.0;
  std::string encoding;
  std::vector<std::uint8_t> data;
  std::vector<Contribution> contributors;
};

/// mapmerge::GlobalMapDelta without vendor types, the blocks not yet checked.
struct GlobalDeltaMessage {
  std::uint64_t version = 0;
  std::uint64_t base_version = 0;
  std::uint64_t base_hash = 0;
  std::uint64_t hash = 0;
  double stamp = 0.0;
  std::string frame_id;
  double resolution = 0.0;
  std::vector<BlockPatch> blocks;
  std::size_t bytes = 0;  ///< records' bytes
  std::vector<Contribution> contributors;
};

struct TransportConfig {
  int domain = 0;
  wire::ProfileSpec profile;
  std::string robot_id;           ///< empty: no map writer
  bool receive_global_map = true;
  std::string participant_name;
  std::chrono::milliseconds max_block{200};  ///< max blocking time of our writers
  wire::SecurityOptions security;            ///< DDS Security identity; default: off
};

/// Called on DDS threads: must only hand the data over, never block.
struct TransportEvents {
  std::function<void(Pose&&)> pose;
  std::function<void(GlobalMapMessage&&)> global_map;
  std::function<void(GlobalDeltaMessage&&)> global_delta;
};

class Transport {
 public:
  virtual ~Transport() = default;
  /// Writes one map update (the writer's max blocking time bounds it). False on failure.
  virtual bool write_map(const MapMessage& message) = 0;
  /// Writes a MapRequest. False on failure.
  virtual bool write_request(const std::string& requester, std::uint64_t nonce) = 0;
  /// Servers matched: writers of poses or of the global map seen by our readers.
  virtual int matched_servers() const = 0;
  /// Readers matched by our request writer (a request written before any is matched is lost).
  virtual int matched_request_readers() const = 0;
  /// Waits until the map writer's samples are acknowledged, at most `timeout`.
  virtual bool wait_for_acks(std::chrono::milliseconds timeout) = 0;
};

/// Throw ClientError when the DDS entities cannot be created.
std::unique_ptr<Transport> make_fastdds_transport(const TransportConfig& config, TransportEvents events);
std::unique_ptr<Transport> make_cyclone_transport(const TransportConfig& config, TransportEvents events);

/// Seconds since the epoch from a (sec, nanosec) wire time.
inline double to_seconds(std::int64_t sec, std::uint32_t nanosec) { return double(sec) + 1e-9 * double(nanosec); }

}  // namespace mapmerge::client::detail
