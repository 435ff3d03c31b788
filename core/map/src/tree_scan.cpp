#include "tree_scan.hpp"

#include <array>
#include <cmath>
#include <cstring>

namespace mapmerge::detail {
namespace {

constexpr int kLevels = static_cast<int>(kTreeDepth);  ///< as an int, for depth arithmetic

std::string at(std::size_t pos, int depth) {
  return " (byte " + std::to_string(pos) + ", depth " + std::to_string(depth) + ")";
}

TreeScan fail(DecodeError error, std::string reason) {
  TreeScan scan;
  scan.error = error;
  scan.reason = std::move(reason);
  return scan;
}

/// Walks a depth-first body with an explicit per-level counter of nodes still to read, so hostile
/// input can neither recurse nor run past the buffer. `read_node` consumes one node at `pos` and
/// returns how many of its children follow in the stream (or -1 after filling `scan` on error).
/// `max_follower_depth`: deepest level at which a node may be followed by its own record.
template <std::size_t kNodeBytes, typename ReadNode>
TreeScan walk(const std::uint8_t* data, std::size_t size, std::size_t max_nodes, int max_follower_depth,
              ReadNode read_node) {
  TreeScan scan;
  if (size == 0) return scan;  // an empty tree has no body at all
  std::array<std::uint8_t, kLevels + 2> pending{};
  pending[0] = 1;
  int depth = 0;
  std::size_t pos = 0;
  std::size_t nodes = 1;
  for (;;) {
    while (depth >= 0 && pending[static_cast<std::size_t>(depth)] == 0) --depth;
    if (depth < 0) break;
    --pending[static_cast<std::size_t>(depth)];
    if (size - pos < kNodeBytes) {
      return fail(DecodeError::kTruncated, pos == size ? "body ends before a node" + at(pos, depth)
                                                        : "body ends mid-node" + at(pos, depth));
    }
    std::uint32_t children = 0;
    std::uint32_t followers = 0;
    if (!read_node(data + pos, depth, pos, children, followers, scan)) return scan;
    pos += kNodeBytes;
    if (depth == 0 && children == 0) scan.root_only = true;
    nodes += children;
    if (nodes > max_nodes) {
      return fail(DecodeError::kTooManyNodes,
                  "more than " + std::to_string(max_nodes) + " nodes" + at(pos, depth));
    }
    if (followers > 0) {
      if (depth + 1 > max_follower_depth) {
        return fail(DecodeError::kTooDeep, "tree deeper than 16 levels" + at(pos, depth));
      }
      ++depth;
      pending[static_cast<std::size_t>(depth)] = static_cast<std::uint8_t>(followers);
    }
  }
  if (pos != size) {
    return fail(DecodeError::kTrailingBytes, std::to_string(size - pos) +
                                                 " bytes after the end of the tree" +
                                                 at(pos, 0));
  }
  scan.num_nodes = nodes;
  return scan;
}

}  // namespace

TreeScan scan_binary_body(const std::uint8_t* data, std::size_t size, std::size_t max_nodes, unsigned root_depth) {
  if (root_depth >= kTreeDepth) return fail(DecodeError::kTooDeep, "a subtree below the last level");
  const int top = static_cast<int>(root_depth);
  // Child codes: binary_child_code().
  auto read_node = [top](const std::uint8_t* p, int depth, std::size_t pos, std::uint32_t& children,
                         std::uint32_t& inner, TreeScan& scan) {
    const std::uint64_t child_voxels = std::uint64_t{1} << (3 * (kLevels - 1 - depth - top));
    const double child_width = static_cast<double>(1U << (kLevels - 1 - depth - top));
    for (int i = 0; i < 8; ++i) {
      const unsigned code = binary_child_code(p, static_cast<unsigned>(i));
      children += code != 0;
      inner += code == 3;
      if (code == 2) scan.occupied_voxels += child_voxels;  // pruned leaves count in full
      if (code == 1 || code == 2) scan.fusion_work += leaf_fusion_work(child_width);
    }
    if (children == 0 && depth > 0) {
      scan = fail(DecodeError::kMalformedTree, "inner node without children" + at(pos, depth));
      return false;
    }
    return true;
  };
  // Inner nodes (code 3) have children one level further down: at most at depth 15.
  return walk<2>(data, size, max_nodes, kLevels - 1 - top, read_node);
}

TreeScan scan_full_body(const std::uint8_t* data, std::size_t size, std::size_t max_nodes) {
  // Each node: float log-odds, then a byte whose bit i says child i follows (depth-first).
  auto read_node = [](const std::uint8_t* p, int depth, std::size_t pos, std::uint32_t& children,
                      std::uint32_t& followers, TreeScan& scan) {
    float value = 0.0F;
    std::memcpy(&value, p, sizeof(value));
    if (!std::isfinite(value)) {
      scan = fail(DecodeError::kBadValue, "log-odds value is not finite" + at(pos, depth));
      return false;
    }
    for (int i = 0; i < 8; ++i) children += (p[4] >> i) & 1U;
    followers = children;
    if (children == 0 && depth > 0) {
      if (value >= 0.0F) scan.occupied_voxels += std::uint64_t{1} << (3 * (kLevels - depth));
      scan.fusion_work += leaf_fusion_work(static_cast<double>(1U << (kLevels - depth)));
    }
    return true;
  };
  return walk<5>(data, size, max_nodes, kLevels, read_node);
}

}  // namespace mapmerge::detail
