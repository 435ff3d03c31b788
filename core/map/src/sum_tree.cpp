#include "sum_tree.hpp"

#include <algorithm>

#include "octree_internals.hpp"

namespace mapmerge::detail {

SumNode* SumTree::new_child(Cursor& cursor, SumNode* node, unsigned i, std::int64_t value) {
  // As OcTreeBaseImpl::createNodeChild, but counted in the cursor: writers of disjoint blocks
  // may create nodes at once.
  auto& children = node->*NodeInternals<SumNode>::kChildren;
  if (children == nullptr) {
    children = new octomap::AbstractOcTreeNode*[8];
    std::fill_n(children, 8, nullptr);
  }
  auto* child = new SumNode(value);
  children[i] = child;
  ++cursor.created;
  return child;
}

SumNode* SumTree::descend(Cursor& cursor, const octomap::OcTreeKey& key, unsigned depth, bool& fresh) {
  fresh = false;
  if (root == nullptr) {
    root = new SumNode(0);
    ++tree_size;
    size_changed = true;
    cursor.depth = 0;
    fresh = true;
  }
  cursor.path[0] = root;
  // The cached path is shared down to the level of the highest bit where the keys differ.
  const unsigned diff = static_cast<unsigned>((key[0] ^ cursor.key[0]) | (key[1] ^ cursor.key[1]) |
                                              (key[2] ^ cursor.key[2]));
  unsigned shared = kTreeDepth;
  for (unsigned bits = diff; bits != 0; bits >>= 1) --shared;
  const unsigned d = std::min({shared, depth, cursor.depth});
  SumNode* node = cursor.path[d];
  for (unsigned level = d; level < depth; ++level) {
    const unsigned pos = octomap::computeChildIdx(key, static_cast<int>(kTreeDepth - 1 - level));
    if (nodeChildExists(node, pos)) {
      node = getNodeChild(node, pos);
    } else if (!fresh && !nodeHasChildren(node) && node->getValue() != 0) {
      // A uniform block: its children inherit its sum (OcTreeBaseImpl::expandNode).
      for (unsigned k = 0; k < 8; ++k) new_child(cursor, node, k, node->getValue());
      node = getNodeChild(node, pos);
    } else {
      node = new_child(cursor, node, pos, 0);  // no evidence yet
      fresh = true;
    }
    cursor.path[level + 1] = node;
  }
  cursor.key = key;
  cursor.depth = depth;
  return node;
}

void SumTree::add_subtree(Cursor& cursor, SumNode* node, std::int64_t delta) {
  const auto& children = node->*NodeInternals<SumNode>::kChildren;
  if (children == nullptr) {
    node->setValue(node->getValue() + delta);
    return;
  }
  for (unsigned i = 0; i < 8; ++i) {
    if (children[i] != nullptr) {
      add_subtree(cursor, static_cast<SumNode*>(children[i]), delta);  // depth <= 16: bounded recursion
    } else {
      new_child(cursor, node, i, delta);
    }
  }
}

void SumTree::add_at(Cursor& cursor, const octomap::OcTreeKey& key, unsigned level, std::int64_t delta) {
  bool fresh = false;
  SumNode* node = descend(cursor, key, kTreeDepth - level, fresh);
  if (fresh) {
    node->setValue(delta);
  } else {
    add_subtree(cursor, node, delta);
  }
}

void SumTree::count_created(Cursor& cursor) {
  if (cursor.created == 0) return;
  tree_size += cursor.created;
  size_changed = true;
  cursor.created = 0;
}

void SumTree::prepare_block(std::uint64_t block) {
  bool fresh = false;
  descend(cursor_, patch_block_key(block), kBlockDepth, fresh);
  count_created(cursor_);
}

void SumTree::account_writer(const BlockWriter& writer) {
  tree_size += writer.cursor_.created;
  size_changed = true;
  cursor_.depth = 0;  // writers may have expanded nodes on add()'s cached path
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
  add_at(cursor_, key, level, delta);
  count_created(cursor_);
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
  cursor_.depth = 0;
}

}  // namespace mapmerge::detail
