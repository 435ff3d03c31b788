#include "sum_tree.hpp"

#include <algorithm>

#include "octree_internals.hpp"

namespace mapmerge::detail {

SumNode* SumTree::new_child(SumNode* node, unsigned i, std::int64_t value) {
  SumNode* child = createNodeChild(node, i);  // a SumNode() holds 0
  child->setValue(value);
  return child;
}

SumNode* SumTree::descend(const octomap::OcTreeKey& key, unsigned depth, bool& fresh) {
  fresh = false;
  if (root == nullptr) {
    root = new SumNode(0);
    ++tree_size;
    size_changed = true;
    path_depth_ = 0;
    fresh = true;
  }
  path_[0] = root;
  // The cached path is shared down to the level of the highest bit where the keys differ.
  const unsigned diff = static_cast<unsigned>((key[0] ^ path_key_[0]) | (key[1] ^ path_key_[1]) |
                                              (key[2] ^ path_key_[2]));
  unsigned shared = kTreeDepth;
  for (unsigned bits = diff; bits != 0; bits >>= 1) --shared;
  const unsigned d = std::min({shared, depth, path_depth_});
  SumNode* node = path_[d];
  for (unsigned level = d; level < depth; ++level) {
    const unsigned pos = octomap::computeChildIdx(key, static_cast<int>(kTreeDepth - 1 - level));
    if (nodeChildExists(node, pos)) {
      node = getNodeChild(node, pos);
    } else if (!fresh && !nodeHasChildren(node) && node->getValue() != 0) {
      expandNode(node);  // a uniform block: its children inherit its sum
      node = getNodeChild(node, pos);
    } else {
      node = new_child(node, pos, 0);  // no evidence yet
      fresh = true;
    }
    path_[level + 1] = node;
  }
  path_key_ = key;
  path_depth_ = depth;
  return node;
}

void SumTree::add_subtree(SumNode* node, std::int64_t delta) {
  if (!nodeHasChildren(node)) {
    node->setValue(node->getValue() + delta);
    return;
  }
  for (unsigned i = 0; i < 8; ++i) {
    if (nodeChildExists(node, i)) {
      add_subtree(getNodeChild(node, i), delta);  // depth <= 16: bounded recursion
    } else {
      new_child(node, i, delta);
    }
  }
}

namespace {
/// A region of 2^level voxels a side, named by its level and its key shifted right by level.
std::uint64_t region_id(const octomap::OcTreeKey& key, unsigned level) {
  return std::uint64_t{level} << 48 | std::uint64_t{key[0]} >> level | (std::uint64_t{key[1]} >> level) << 16 |
         (std::uint64_t{key[2]} >> level) << 32;
}
}  // namespace

void SumTree::note_change(const octomap::OcTreeKey& key, unsigned level) {
  if (all_changed_) return;
  if (level <= kTreeDepth - kBlockDepth) {
    const std::uint64_t block = block_of(key);
    if (block != last_block_) changed_blocks_.insert(block);
    last_block_ = block;
    return;
  }
  changed_regions_.insert(region_id(key, level));
  region_levels_ |= 1U << level;
}

bool SumTree::changed(std::uint64_t block) const {
  if (all_changed_ || changed_blocks_.count(block) != 0) return true;
  if (region_levels_ == 0) return false;
  constexpr unsigned kBlockLevel = kTreeDepth - kBlockDepth;
  const octomap::OcTreeKey key = patch_block_key(block);
  for (unsigned level = kBlockLevel + 1; level <= kTreeDepth; ++level) {
    if ((region_levels_ & (1U << level)) != 0 && changed_regions_.count(region_id(key, level)) != 0) return true;
  }
  return false;
}

std::optional<std::vector<std::uint64_t>> SumTree::changed_blocks(std::size_t max) const {
  if (all_changed_ || changed_blocks_.size() > max) return std::nullopt;
  std::unordered_set<std::uint64_t> blocks(changed_blocks_);
  for (const std::uint64_t region : changed_regions_) {
    const auto level = static_cast<unsigned>(region >> 48);
    const unsigned shift = level - (kTreeDepth - kBlockDepth);  // block bits inside the region
    const std::uint64_t n = std::uint64_t{1} << shift;          // blocks per side
    if (blocks.size() + n * n * n > max) return std::nullopt;
    std::uint64_t first[3];
    for (unsigned a = 0; a < 3; ++a) first[a] = ((region >> (16 * a)) & 0xFFFFU) << shift;
    for (std::uint64_t z = 0; z < n; ++z) {
      for (std::uint64_t y = 0; y < n; ++y) {
        for (std::uint64_t x = 0; x < n; ++x) {
          blocks.insert((first[0] + x) | (first[1] + y) << 16 | (first[2] + z) << 32);
        }
      }
    }
  }
  return std::vector<std::uint64_t>(blocks.begin(), blocks.end());
}

void SumTree::forget_changes() {
  changed_blocks_.clear();
  changed_regions_.clear();
  region_levels_ = 0;
  all_changed_ = false;
  last_block_ = ~std::uint64_t{0};
}

void SumTree::add(const octomap::OcTreeKey& key, unsigned level, std::int64_t delta) {
  note_change(key, level);
  bool fresh = false;
  SumNode* node = descend(key, kTreeDepth - level, fresh);
  if (fresh) {
    node->setValue(delta);
  } else {
    add_subtree(node, delta);
  }
}

void SumTree::drop_child(SumNode* parent, unsigned i) {
  std::size_t deleted = 0;
  drop_child(parent, i, deleted);
  account(deleted);
}

void SumTree::drop_child(SumNode* parent, unsigned i, std::size_t& deleted) {
  SumNode* child = getNodeChild(parent, i);
  for (unsigned k = 0; k < 8; ++k) {
    if (nodeChildExists(child, k)) drop_child(child, k, deleted);  // depth <= 16: bounded recursion
  }
  free_children_array(child);
  parent->delete_child(i);
  ++deleted;
}

bool SumTree::prune(SumNode* node, std::size_t& deleted) {
  if (!isNodeCollapsible(node)) return false;  // as OcTreeBaseImpl::pruneNode
  node->copyData(*getNodeChild(node, 0));
  for (unsigned i = 0; i < 8; ++i) node->delete_child(i);
  free_children_array(node);
  deleted += 8;
  return true;
}

void SumTree::drop_all() {
  clear();
  all_changed_ = true;
  path_depth_ = 0;
}

}  // namespace mapmerge::detail
