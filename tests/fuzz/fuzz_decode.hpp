#pragma once
// The fuzz target's logic, shared with the regression test that replays tests/fuzz/regressions/.
//
// Input: a `.bt`/`.ot` file or a zstd frame is decoded as such (so the seed corpus can be real
// map files); anything else is a ROS 2 body whose first byte picks the binary flag, the tree id
// and one of a few resolutions (good and hostile).
// Invariant checked on every accepted input: encoding the tree and decoding it again gives the
// same node count and the same bytes. A broken invariant aborts (the fuzzer reports it).
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <vector>

#include "mapmerge/map/bounds.hpp"
#include "mapmerge/map/held_map.hpp"
#include "mapmerge/map/leaf_set.hpp"
#include "mapmerge/map/map_codec.hpp"

namespace mapmerge::fuzz {

inline DecodeLimits fuzz_limits() {
  DecodeLimits limits;
  limits.max_bytes = 8u << 20;  // keep each run small; the logic is the same at 100 MB
  limits.max_nodes = 2'000'000;
  return limits;
}

/// Returns 1 if `r` was accepted, 0 if rejected; aborts if a rejection or a tree is inconsistent.
inline int check_round_trip(const DecodeResult& r, const DecodeLimits& limits) {
  if (!r.ok()) {
    if (r.reason.empty() || r.tree) std::abort();  // a rejection always says why, holds no tree
    return 0;
  }
  if (!r.tree || r.tree->size() != r.num_nodes) std::abort();
  const auto bytes = encode_map(*r.tree, Encoding::kOctomapBt);
  const auto again = decode_map(bytes, Encoding::kOctomapBt, limits);
  if (!again.ok() || again.num_nodes != r.num_nodes) std::abort();
  if (encode_map(*again.tree, Encoding::kOctomapBt) != bytes) std::abort();
  return 1;
}

/// check_map()/check_tree_body() must accept and reject exactly what decoding does, the leaves
/// read off a checked map's body must be the decoded tree's (bounds, occupied and free leaf
/// counts), and the tree it builds later must be the decoded tree; aborts otherwise. Returns
/// `r`'s verdict.
inline int check_agrees(const DecodeResult& r, const CheckedMap& c, const DecodeLimits& limits) {
  if (c.error != r.error || c.empty != r.empty || (c.ok() && !c.empty) != (c.map != nullptr)) std::abort();
  if (c.map) {
    if (c.map->num_nodes() != r.num_nodes || c.map->resolution() != r.tree->getResolution()) std::abort();
    if (!c.map->has_tree()) {  // what is read off the body (binary or full) is what the tree holds
      const Eigen::AlignedBox3d box = leaf_bounds(*c.map), tree_box = leaf_bounds(*r.tree);
      if (box.isEmpty() != tree_box.isEmpty() || (!box.isEmpty() && (box.min() != tree_box.min() || box.max() != tree_box.max())))
        std::abort();
      for (const LeafState state : {LeafState::kOccupied, LeafState::kFree}) {
        if (LeafSet::of(*c.map, state).size() != LeafSet::of(*r.tree, state).size()) std::abort();
      }
    }
    if (encode_map(*c.map->tree(), Encoding::kOctomapBt) != encode_map(*r.tree, Encoding::kOctomapBt)) std::abort();
  }
  return check_round_trip(r, limits);
}

/// Decodes one fuzz input every way it can be read; returns how many decodings accepted it.
inline int decode_one(const std::uint8_t* data, std::size_t size) {
  static const DecodeLimits limits = fuzz_limits();
  auto starts_with = [&](const char* prefix) {
    const std::size_t n = std::strlen(prefix);
    return size >= n && std::memcmp(data, prefix, n) == 0;
  };
  if (starts_with("# Octomap")) {
    return check_agrees(decode_map(data, size, Encoding::kOctomapBt, limits),
                        check_map(data, size, Encoding::kOctomapBt, limits), limits) +
           check_agrees(decode_map(data, size, Encoding::kOctomapOt, limits),
                        check_map(data, size, Encoding::kOctomapOt, limits), limits);
  }
  if (starts_with("\x28\xB5\x2F\xFD")) {
    return check_agrees(decode_map(data, size, Encoding::kOctomapBtZstd, limits),
                        check_map(data, size, Encoding::kOctomapBtZstd, limits), limits);
  }
  if (size == 0) return 0;
  static const double resolutions[] = {0.05, 0.1, 0.02, 1.0, 0.0, -0.05,
                                       std::numeric_limits<double>::quiet_NaN(), 1e-300};
  const bool binary = (data[0] & 1) == 0;
  const double res = resolutions[(data[0] >> 1) & 7];
  const char* id = (data[0] & 0x80) != 0 ? "ColorOcTree" : "OcTree";
  const std::vector<std::uint8_t> body(data + 1, data + size);
  return check_agrees(decode_tree_body(id, res, binary, body, limits), check_tree_body(id, res, binary, body, limits),
                      limits);
}

}  // namespace mapmerge::fuzz
