#pragma once
/// Morton codes of octree keys (internal to mapmerge_core): per level, from the root down, a
/// key's child index (x bit 0, y bit 1, z bit 2), so that codes in increasing order are the
/// order of a depth-first walk of the tree (OctoMap's child order).

#include <cstdint>

namespace mapmerge::detail {

/// The 16 bits of v spread to every third bit.
inline std::uint64_t morton_spread(std::uint64_t v) {
  v &= 0xFFFFU;
  v = (v | v << 32) & 0x1F00000000FFFFULL;
  v = (v | v << 16) & 0x1F0000FF0000FFULL;
  v = (v | v << 8) & 0x100F00F00F00F00FULL;
  v = (v | v << 4) & 0x10C30C30C30C30C3ULL;
  v = (v | v << 2) & 0x1249249249249249ULL;
  return v;
}

/// The inverse of morton_spread().
inline std::uint64_t morton_compact(std::uint64_t v) {
  v &= 0x1249249249249249ULL;
  v = (v ^ (v >> 2)) & 0x10C30C30C30C30C3ULL;
  v = (v ^ (v >> 4)) & 0x100F00F00F00F00FULL;
  v = (v ^ (v >> 8)) & 0x1F0000FF0000FFULL;
  v = (v ^ (v >> 16)) & 0x1F00000000FFFFULL;
  v = (v ^ (v >> 32)) & 0xFFFFU;
  return v;
}

/// The Morton code of the key (x, y, z).
inline std::uint64_t morton_code(std::uint64_t x, std::uint64_t y, std::uint64_t z) {
  return morton_spread(x) | (morton_spread(y) << 1) | (morton_spread(z) << 2);
}

}  // namespace mapmerge::detail
