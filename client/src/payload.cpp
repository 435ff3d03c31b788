// The vendor-free payload side of a client: serialising map updates, validating received
// global maps, session ids, option checks.

#include <random>
#include <sstream>

#include "client_core.hpp"
#include "mapmerge/map/map_codec.hpp"
#include "mapmerge/wire/topics.hpp"

namespace mapmerge::client::detail {
namespace {

std::string random_hex(int digits) {
  std::random_device rd;
  std::mt19937_64 rng((std::uint64_t(rd()) << 32) ^ rd() ^
                      std::uint64_t(std::chrono::steady_clock::now().time_since_epoch().count()));
  std::ostringstream ss;
  ss << std::hex;
  for (int i = 0; i < digits; ++i) ss << (rng() & 0xF);
  return ss.str();
}

}  // namespace

wire::SecurityOptions security_options(const Options& options) {
  const std::string enclave = options.enclave.empty() ? options.robot_id : options.enclave;
  if (options.keystore.empty()) return wire::SecurityOptions::from_environment(enclave);
  return wire::SecurityOptions{options.keystore, enclave};
}

const std::string& process_session_id() {
  static const std::string id = random_hex(16);
  return id;
}

MapMessage make_map_message(const octomap::OcTree& tree, const Options& options,
                            const std::string& session_id, std::uint64_t sequence_number) {
  const Encoding encoding = options.zstd ? Encoding::kOctomapBtZstd : Encoding::kOctomapBt;
  EncodeOptions encode_options;
  encode_options.zstd_level = options.zstd_level;
  MapMessage m;
  m.data = encode_map(tree, encoding, encode_options);
  m.encoding = to_string(encoding);
  m.robot_id = options.robot_id;
  m.session_id = session_id;
  m.sequence_number = sequence_number;
  const auto now = std::chrono::system_clock::now().time_since_epoch();
  const auto ns = std::chrono::duration_cast<std::chrono::nanoseconds>(now).count();
  m.stamp_sec = static_cast<std::int32_t>(ns / 1000000000);
  m.stamp_nanosec = static_cast<std::uint32_t>(ns % 1000000000);
  m.frame_id = options.frame_id;
  m.resolution = tree.getResolution();
  return m;
}

std::shared_ptr<const GlobalMap> decode_global_map(GlobalMapMessage&& message, std::size_t max_bytes,
                                                   std::string& error) {
  DecodeLimits limits;
  limits.max_bytes = max_bytes;
  DecodeResult decoded = decode_map(message.data, message.encoding, limits);
  if (!decoded.ok()) {
    error = "global map version " + std::to_string(message.version) + " rejected: " + decoded.reason;
    return nullptr;
  }
  auto map = std::make_shared<GlobalMap>();
  map->version = message.version;
  map->frame_id = std::move(message.frame_id);
  map->resolution = message.resolution;
  map->stamp = message.stamp;
  map->encoding = std::move(message.encoding);
  map->payload_bytes = message.data.size();
  map->contributors = std::move(message.contributors);
  map->tree = std::shared_ptr<const octomap::OcTree>(std::move(decoded.tree));
  return map;
}

}  // namespace mapmerge::client::detail

namespace mapmerge::client {

std::string check_options(const Options& options) {
  if (!options.robot_id.empty() && !wire::is_valid_robot_id(options.robot_id)) {
    return "invalid robot id '" + options.robot_id +
           "' (a letter, then letters, digits or '_', at most 64 characters)";
  }
  if (options.domain < 0 || options.domain > 232) {
    return "DDS domain " + std::to_string(options.domain) + " out of range 0..232";
  }
  if (options.zstd_level < 1 || options.zstd_level > 19) {
    return "zstd level " + std::to_string(options.zstd_level) + " out of range 1..19";
  }
  try {
    wire::ProfileSpec::parse(options.profile);
  } catch (const std::invalid_argument& e) {
    return e.what();
  }
  const wire::SecurityOptions security = detail::security_options(options);
  if (security.enabled()) {
    if (security.enclave.empty()) return "DDS Security needs an enclave (an observer has no robot id to use)";
    try {
      security.files();
    } catch (const std::invalid_argument& e) {
      return e.what();
    }
  }
  return {};
}

}  // namespace mapmerge::client
