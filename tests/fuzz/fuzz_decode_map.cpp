// libFuzzer target over the map-decoding entry points (issue 7): decode_map() for every wire
// encoding and decode_tree_body() for the ROS 2 message path.
//
// Input: a `.bt`/`.ot` file or a zstd frame is decoded as such (so the seed corpus can be real
// map files); anything else is a ROS 2 body whose first byte picks the binary flag and one of a
// few resolutions (good and hostile).
// Invariant checked on every accepted input: encoding the tree and decoding it again gives the
// same node count and the same bytes.
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <vector>

#include "mapmerge/map/map_codec.hpp"

namespace {

mapmerge::DecodeLimits fuzz_limits() {
  mapmerge::DecodeLimits limits;
  limits.max_bytes = 8u << 20;  // keep each run small; the logic is the same at 100 MB
  limits.max_nodes = 2'000'000;
  return limits;
}

void check_round_trip(const mapmerge::DecodeResult& r, const mapmerge::DecodeLimits& limits) {
  if (!r.ok()) {
    if (r.reason.empty() || r.tree) std::abort();  // a rejection always says why, holds no tree
    return;
  }
  if (!r.tree || r.tree->size() != r.num_nodes) std::abort();
  const auto bytes = mapmerge::encode_map(*r.tree, mapmerge::Encoding::kOctomapBt);
  const auto again = mapmerge::decode_map(bytes, mapmerge::Encoding::kOctomapBt, limits);
  if (!again.ok() || again.num_nodes != r.num_nodes) std::abort();
  if (mapmerge::encode_map(*again.tree, mapmerge::Encoding::kOctomapBt) != bytes) std::abort();
}

bool starts_with(const std::uint8_t* data, std::size_t size, const char* prefix) {
  const std::size_t n = std::strlen(prefix);
  return size >= n && std::memcmp(data, prefix, n) == 0;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  static const mapmerge::DecodeLimits limits = fuzz_limits();
  using mapmerge::Encoding;
  if (starts_with(data, size, "# Octomap")) {
    check_round_trip(mapmerge::decode_map(data, size, Encoding::kOctomapBt, limits), limits);
    check_round_trip(mapmerge::decode_map(data, size, Encoding::kOctomapOt, limits), limits);
    return 0;
  }
  if (size >= 4 && data[0] == 0x28 && data[1] == 0xB5 && data[2] == 0x2F && data[3] == 0xFD) {
    check_round_trip(mapmerge::decode_map(data, size, Encoding::kOctomapBtZstd, limits), limits);
    return 0;
  }
  if (size == 0) return 0;
  static const double resolutions[] = {0.05, 0.1, 0.02, 1.0, 0.0, -0.05,
                                       std::numeric_limits<double>::quiet_NaN(), 1e-300};
  const bool binary = (data[0] & 1) == 0;
  const double res = resolutions[(data[0] >> 1) & 7];
  const char* id = (data[0] & 0x80) != 0 ? "ColorOcTree" : "OcTree";
  check_round_trip(mapmerge::decode_tree_body(id, res, binary, data + 1, size - 1, limits), limits);
  return 0;
}
