#pragma once
/// The leaves of a held map read off its body, binary (`.bt`) or full (`.ot`), without its octree
/// (internal to mapmerge_core).

#include <cstdint>

#include "mapmerge/map/held_map.hpp"
#include "tree_scan.hpp"

namespace mapmerge::detail {

/// OcTree::isNodeOccupied at OctoMap's default occupancy threshold (0.5, log-odds 0): how a full
/// body's leaf reads, as the tree decoded from it would read it.
inline bool occupied_log_odds(float log_odds) { return log_odds >= 0.0F; }

/// Calls `leaf(log_odds, occupied, depth, x, y, z)` for every known leaf of `map`'s body, in
/// depth-first child order, with (depth, x, y, z) as for_each_binary_leaf() gives them. A binary
/// body's leaf carries the log-odds its state stands for (map.free_log_odds() or
/// map.occupied_log_odds()), its state its child code; a full body's leaf its own log-odds.
/// Returns false, calling nothing, when the map holds no body (only a tree).
template <class Leaf>
bool for_each_body_leaf(const HeldMap& map, Leaf&& leaf) {
  if (const auto& body = map.binary_body()) {
    const float values[3] = {0.0F, map.free_log_odds(), map.occupied_log_odds()};  // by child code
    for_each_binary_leaf(*body, [&](unsigned code, unsigned depth, std::uint32_t x, std::uint32_t y,
                                    std::uint32_t z) { leaf(values[code], code == 2U, depth, x, y, z); });
    return true;
  }
  if (const auto& full = map.full_body()) {
    for_each_full_leaf(*full, [&](float log_odds, unsigned depth, std::uint32_t x, std::uint32_t y, std::uint32_t z) {
      leaf(log_odds, occupied_log_odds(log_odds), depth, x, y, z);
    });
    return true;
  }
  return false;
}

}  // namespace mapmerge::detail
