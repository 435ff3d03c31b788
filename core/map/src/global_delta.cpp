#include "mapmerge/map/global_delta.hpp"

#include <algorithm>
#include <unordered_set>

#include "octree_internals.hpp"
#include "tree_scan.hpp"

namespace mapmerge {
namespace {

using detail::kTreeDepth;

/// Child index of the node at `depth` on the way to `key`.
unsigned child_at(const octomap::OcTreeKey& key, unsigned depth) {
  return octomap::computeChildIdx(key, static_cast<int>(kTreeDepth - 1 - depth));
}

class Patcher {
 public:
  explicit Patcher(octomap::OcTree& tree) : tree_(tree) {}

  void put(const BlockPatch& patch) {
    const octomap::OcTreeKey key = patch_block_key(patch.block);
    octomap::OcTreeNode* node = root();
    if (node == nullptr) {
      if (patch.state == BlockState::kUnknown) return;
      node = make_root();
    }
    for (unsigned depth = 0; depth < kPatchBlockDepth; ++depth) {
      const unsigned i = child_at(key, depth);
      if (tree_.nodeChildExists(node, i)) {
        octomap::OcTreeNode* child = tree_.getNodeChild(node, i);
        if (!tree_.nodeHasChildren(child) && depth + 1 < kPatchBlockDepth) {
          tree_.expandNode(child);  // a uniform region larger than a block: its blocks inherit its state
        }
        node = child;
      } else {
        if (patch.state == BlockState::kUnknown) return;  // unknown already
        node = tree_.createNodeChild(node, i);
      }
    }
    erase_children(node);
    switch (patch.state) {
      case BlockState::kUnknown: break;  // removed by canonical(): a node without children
      case BlockState::kFree: node->setLogOdds(tree_.getClampingThresMinLog()); break;
      case BlockState::kOccupied: node->setLogOdds(tree_.getClampingThresMaxLog()); break;
      case BlockState::kMixed: {
        const std::uint8_t* next = patch.records.data();
        read(node, next);
        node->setLogOdds(node->getMaxChildLogOdds());
        break;
      }
    }
    if (patch.state == BlockState::kUnknown) unknown_.push_back(patch.block);
    patched_.push_back(patch.block);
  }

  /// Restores the form decode_map() builds, bottom-up along every patched block's path: a node
  /// without children is unknown space (removed), one whose 8 children are equal leaves is a leaf,
  /// any other inner node holds the maximum of its children (the root: occupied, as decoded).
  void canonical() {
    for (std::uint64_t block : unknown_) remove_if_empty(block, kPatchBlockDepth);
    std::unordered_set<std::uint64_t> parents;  // nodes at `depth`, named by their key prefix
    for (std::uint64_t block : patched_) parents.insert(parent_of(block));
    for (unsigned depth = kPatchBlockDepth - 1; depth >= 1; --depth) {
      std::unordered_set<std::uint64_t> up;
      for (std::uint64_t prefix : parents) {
        fix(prefix, depth);
        up.insert(parent_of(prefix));
      }
      parents.swap(up);
    }
    octomap::OcTreeNode* r = root();
    if (r == nullptr) return;
    if (!tree_.nodeHasChildren(r)) {
      tree_.clear();
      return;
    }
    r->setLogOdds(tree_.getClampingThresMaxLog());
  }

 private:
  octomap::OcTreeNode* root() { return tree_.getRoot(); }

  octomap::OcTreeNode* make_root() {
    octomap::OcTreeNode* r = detail::create_root(tree_);
    r->setLogOdds(tree_.getClampingThresMaxLog());
    return r;
  }

  /// The prefix (key >> bits below `depth`, packed as block ids are) of the parent of a node.
  static std::uint64_t parent_of(std::uint64_t prefix) {
    return (prefix & 0xFFFFU) >> 1 | (((prefix >> 16) & 0xFFFFU) >> 1) << 16 | (((prefix >> 32) & 0xFFFFU) >> 1) << 32;
  }

  static octomap::OcTreeKey prefix_key(std::uint64_t prefix, unsigned depth) {
    const unsigned s = kTreeDepth - depth;
    return octomap::OcTreeKey(static_cast<octomap::key_type>((prefix & 0xFFFFU) << s),
                              static_cast<octomap::key_type>(((prefix >> 16) & 0xFFFFU) << s),
                              static_cast<octomap::key_type>(((prefix >> 32) & 0xFFFFU) << s));
  }

  /// The node at `depth` named by `prefix` and its parent (nulls where the path ends).
  std::pair<octomap::OcTreeNode*, octomap::OcTreeNode*> find(std::uint64_t prefix, unsigned depth) {
    const octomap::OcTreeKey key = prefix_key(prefix, depth);
    octomap::OcTreeNode* parent = nullptr;
    octomap::OcTreeNode* node = root();
    for (unsigned d = 0; d < depth && node != nullptr; ++d) {
      const unsigned i = child_at(key, d);
      parent = node;
      node = tree_.nodeChildExists(node, i) ? tree_.getNodeChild(node, i) : nullptr;
    }
    return {node, parent};
  }

  void remove_if_empty(std::uint64_t prefix, unsigned depth) {
    auto [node, parent] = find(prefix, depth);
    if (node == nullptr || parent == nullptr || tree_.nodeHasChildren(node)) return;
    detail::free_children_array(node);
    tree_.deleteNodeChild(parent, child_at(prefix_key(prefix, depth), depth - 1));
  }

  void fix(std::uint64_t prefix, unsigned depth) {
    auto [node, parent] = find(prefix, depth);
    if (node == nullptr) return;
    if (!tree_.nodeHasChildren(node)) {  // all its blocks went unknown
      detail::free_children_array(node);
      tree_.deleteNodeChild(parent, child_at(prefix_key(prefix, depth), depth - 1));
      return;
    }
    if (tree_.pruneNode(node)) return;  // 8 equal leaves: one leaf
    node->setLogOdds(node->getMaxChildLogOdds());
  }

  void erase_children(octomap::OcTreeNode* node) {
    if (node->*detail::NodeInternals<octomap::OcTreeNode>::kChildren == nullptr) return;  // no array
    for (unsigned i = 0; i < 8; ++i) {
      if (!tree_.nodeChildExists(node, i)) continue;
      erase_children(tree_.getNodeChild(node, i));  // depth <= 16: bounded recursion
      tree_.deleteNodeChild(node, i);
    }
    detail::free_children_array(node);
  }


  /// Reads one checked subtree's records into `node` as decode_map() does: leaves at the
  /// clamping thresholds, inner nodes the maximum of their children.
  void read(octomap::OcTreeNode* node, const std::uint8_t*& next) {
    const std::uint8_t* record = next;
    next += 2;
    unsigned inner = 0;
    for (unsigned i = 0; i < 8; ++i) {
      const unsigned bits = detail::binary_child_code(record, i);
      if (bits == 0) continue;
      octomap::OcTreeNode* child = tree_.createNodeChild(node, i);
      child->setLogOdds(bits == 1 ? tree_.getClampingThresMinLog() : tree_.getClampingThresMaxLog());
      if (bits == 3) inner |= 1U << i;
    }
    for (unsigned i = 0; i < 8; ++i) {
      if ((inner & (1U << i)) == 0) continue;
      octomap::OcTreeNode* child = tree_.getNodeChild(node, i);
      read(child, next);  // checked: at most 16 - kPatchBlockDepth levels
      child->setLogOdds(child->getMaxChildLogOdds());
    }
  }

  octomap::OcTree& tree_;
  std::vector<std::uint64_t> patched_;  ///< every patched block
  std::vector<std::uint64_t> unknown_;  ///< the patched blocks that are unknown now
};

/// Checks the records of one block's subtree (a body whose root sits at kPatchBlockDepth, with
/// at least one child): well formed, every byte used. Returns the number of nodes, or 0 after
/// setting `error`.
std::size_t check_records(const std::vector<std::uint8_t>& records, std::size_t max_nodes, std::string& error) {
  const detail::TreeScan scan = detail::scan_binary_body(records.data(), records.size(), max_nodes, kPatchBlockDepth);
  if (scan.error != DecodeError::kNone) {
    error = scan.reason;
  } else if (scan.num_nodes == 0) {
    error = "records end before a node (byte 0)";
  } else if (scan.root_only) {
    error = "a record without children (byte 0)";
  } else {
    return scan.num_nodes;
  }
  return 0;
}

}  // namespace

std::uint64_t payload_hash(const std::uint8_t* data, std::size_t size) {
  std::uint64_t h = 1469598103934665603ULL;
  for (std::size_t i = 0; i < size; ++i) h = (h ^ data[i]) * 1099511628211ULL;
  return h;
}

std::string check_block_patches(const std::vector<BlockPatch>& patches, std::size_t max_nodes) {
  constexpr std::uint64_t kAxisBlocks = std::uint64_t{1} << kPatchBlockDepth;
  std::unordered_set<std::uint64_t> seen;
  seen.reserve(patches.size());
  std::size_t nodes = 0;
  for (std::size_t k = 0; k < patches.size(); ++k) {
    const BlockPatch& p = patches[k];
    const std::string which = "block patch " + std::to_string(k) + ": ";
    if ((p.block & 0xFFFFU) >= kAxisBlocks || ((p.block >> 16) & 0xFFFFU) >= kAxisBlocks ||
        ((p.block >> 32) & 0xFFFFU) >= kAxisBlocks || (p.block >> 48) != 0) {
      return which + "block id " + std::to_string(p.block) + " outside the key space";
    }
    if (!seen.insert(p.block).second) return which + "block " + std::to_string(p.block) + " patched twice";
    const auto state = static_cast<unsigned>(p.state);
    if (state > 3) return which + "unknown block state " + std::to_string(state);
    if (p.state != BlockState::kMixed) {
      if (!p.records.empty()) return which + "a uniform block with records";
      ++nodes;
    } else {
      std::string error;
      const std::size_t n = check_records(p.records, max_nodes, error);
      if (n == 0) return which + error;
      nodes += n;
    }
    if (nodes > max_nodes) return "block patches hold more than " + std::to_string(max_nodes) + " nodes";
  }
  return {};
}

void apply_block_patches(octomap::OcTree& tree, const std::vector<BlockPatch>& patches) {
  Patcher patcher(tree);
  for (const BlockPatch& p : patches) patcher.put(p);
  patcher.canonical();
}

}  // namespace mapmerge
