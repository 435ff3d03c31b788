#pragma once
/// Non-recursive structural checks of OctoMap tree bodies (internal to mapmerge_core).

#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <string>
#include <vector>

#include <octomap/OcTree.h>

#include "mapmerge/map/map_codec.hpp"
#include "octree_internals.hpp"

namespace mapmerge::detail {

/// Upper bound of the target voxel visits fusing one leaf `n` target voxels wide costs: all its
/// voxels when small, otherwise its (rotated, inflated) surface; the interior goes in blocks.
inline double leaf_fusion_work(double n) {
  return n <= 4 ? (n + 1) * (n + 1) * (n + 1) : 27 * (n + 1) * (n + 1);
}

/// Child i's code in a binary body's node record (the node's 2 bytes at `record`): bits
/// (2i, 2i+1) of byte i/4; 0 unknown, 1 free leaf, 2 occupied leaf, 3 inner node (whose own
/// record follows, depth-first, in child order).
inline unsigned binary_child_code(const std::uint8_t* record, unsigned i) {
  return (record[i / 4] >> (2 * (i % 4))) & 3U;
}

/// Calls `leaf(code, depth, x, y, z)` for every leaf of a validated binary body (code 1 free,
/// 2 occupied; unknown children are skipped), in depth-first child order; (x, y, z) is the
/// leaf's lowest corner in key units at full depth, `depth` its depth (1..16). The body must
/// have passed scan_binary_body (depth <= 16 bounds the recursion).
template <class Leaf>
void for_each_binary_leaf(const std::vector<std::uint8_t>& body, Leaf&& leaf) {
  struct Walk {
    const std::vector<std::uint8_t>& body;
    Leaf& leaf;
    std::size_t pos = 0;
    void visit(unsigned depth, std::uint32_t x, std::uint32_t y, std::uint32_t z) {
      const std::uint8_t* record = body.data() + pos;
      pos += 2;
      const std::uint32_t half = (1U << kTreeDepth) >> (depth + 1);
      for (unsigned i = 0; i < 8; ++i) {
        const unsigned code = binary_child_code(record, i);
        if (code == 0) continue;
        const std::uint32_t cx = x + ((i & 1U) != 0 ? half : 0), cy = y + ((i & 2U) != 0 ? half : 0),
                            cz = z + ((i & 4U) != 0 ? half : 0);
        if (code == 3) {
          visit(depth + 1, cx, cy, cz);
        } else {
          leaf(code, depth + 1, cx, cy, cz);
        }
      }
    }
  };
  if (body.size() < 2) return;
  Walk{body, leaf}.visit(0, 0, 0, 0);
}

/// Edge [m] of a leaf at `depth` (1..16) of a tree of resolution `res`: OcTree::getNodeSize.
inline double leaf_size(unsigned depth, double res) {
  return res * static_cast<double>(1U << (kTreeDepth - depth));
}

/// Centre coordinate [m] along one axis of the leaf at `depth` whose lowest-corner key on that
/// axis is `corner` (as the walks above give it): OcTree::keyToCoord(key, depth) in the same
/// arithmetic, so the same doubles, (floor((key - centre) / 2^(16 - depth)) + 0.5) * size, or
/// (key - centre + 0.5) * res at depth 16; the corner key makes the floor exact.
inline double leaf_coord(std::uint32_t corner, unsigned depth, double res) {
  constexpr double kCentre = static_cast<double>(1U << (kTreeDepth - 1));
  if (depth == kTreeDepth) return (static_cast<double>(corner) - kCentre + 0.5) * res;
  const double cells = static_cast<double>(1U << (kTreeDepth - depth));
  return (std::floor((static_cast<double>(corner) - kCentre) / cells) + 0.5) * (res * cells);
}

/// Calls `leaf(log_odds, depth, x, y, z)` for every leaf (a node without children, below the
/// root) of a validated full body (OcTree::writeData: per node a float log-odds and a byte whose
/// bit i says child i follows), in depth-first child order, with (x, y, z) as
/// for_each_binary_leaf() gives them. The body must have passed scan_full_body.
template <class Leaf>
void for_each_full_leaf(const std::vector<std::uint8_t>& body, Leaf&& leaf) {
  struct Walk {
    const std::uint8_t* data;
    Leaf& leaf;
    std::size_t pos = 0;
    void visit(unsigned depth, std::uint32_t x, std::uint32_t y, std::uint32_t z) {
      float value = 0.0F;
      std::memcpy(&value, data + pos, sizeof(value));
      const unsigned children = data[pos + sizeof(value)];
      pos += sizeof(value) + 1;
      if (children == 0) {
        if (depth > 0) leaf(value, depth, x, y, z);
        return;
      }
      const std::uint32_t half = (1U << kTreeDepth) >> (depth + 1);
      for (unsigned i = 0; i < 8; ++i) {
        if ((children & (1U << i)) == 0) continue;
        visit(depth + 1, x + ((i & 1U) != 0 ? half : 0), y + ((i & 2U) != 0 ? half : 0),
              z + ((i & 4U) != 0 ? half : 0));
      }
    }
  };
  if (body.size() < sizeof(float) + 1) return;
  Walk{body.data(), leaf}.visit(0, 0, 0, 0);
}

/// What a scan found: the node count of a well-formed body, or why it is not one.
struct TreeScan {
  DecodeError error = DecodeError::kNone;
  std::string reason;
  std::size_t num_nodes = 0;  ///< nodes including the root (0 for an empty body)
  bool root_only = false;     ///< a root without children (no information)
  std::uint64_t occupied_voxels = 0;  ///< occupied space in full-resolution voxels
  double fusion_work = 0.0;           ///< sum of leaf_fusion_work() over the leaves
};

/// Checks a binary body (OcTree::writeBinaryData: per node 2 bytes of 8 two-bit child codes,
/// depth-first). Every byte must be consumed; depth <= 16; at most `max_nodes` nodes. With
/// `root_depth`, the records of a subtree whose root sits at that depth of a tree (a block).
TreeScan scan_binary_body(const std::uint8_t* data, std::size_t size, std::size_t max_nodes,
                          unsigned root_depth = 0);

/// Checks a full body (OcTree::writeData: per node a float log-odds + 1 byte child mask,
/// depth-first). Every byte must be consumed; depth <= 16; values finite; at most `max_nodes`.
TreeScan scan_full_body(const std::uint8_t* data, std::size_t size, std::size_t max_nodes);

}  // namespace mapmerge::detail

namespace mapmerge::detail {

/// Appends `tree`'s binary body exactly as OcTree::writeBinaryData writes it (2 bytes of child
/// codes per inner node, depth-first), without recursion and without OctoMap's debug output.
void append_binary_body(const octomap::OcTree& tree, std::vector<std::uint8_t>& out);

/// Appends the `.bt` text header OcTree::writeBinaryConst writes (id, size, res, data).
void append_binary_header(const octomap::OcTree& tree, std::vector<std::uint8_t>& out);

}  // namespace mapmerge::detail
