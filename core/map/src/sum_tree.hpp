#pragma once
/// The exact evidence sums behind GlobalFusion (internal to mapmerge_core).
///
/// Each voxel holds one int64: (sum of quantised log-odds) * 2^16 + (number of contributions).
/// Both parts add linearly, so adding a contribution and subtracting it again is exact; 0 means
/// no robot has evidence for the voxel (unknown). A leaf above full depth is a uniform block.

#include <array>
#include <cmath>
#include <cstdint>
#include <optional>
#include <unordered_map>
#include <unordered_set>
#include <new>
#include <utility>
#include <vector>

#include <octomap/OcTreeBase.h>
#include <octomap/OcTreeDataNode.h>
#include <tbb/scalable_allocator.h>

#include "mapmerge/map/global_delta.hpp"

namespace mapmerge::detail {

/// A voxel's packed sum (0 when created: no evidence).
class SumNode : public octomap::OcTreeDataNode<std::int64_t> {
 public:
  SumNode() : octomap::OcTreeDataNode<std::int64_t>(0) {}
  explicit SumNode(std::int64_t value) : octomap::OcTreeDataNode<std::int64_t>(value) {}
#ifndef MAPMERGE_SANITIZE_BUILD  // AddressSanitizer must see the nodes (tracked, checked, leak-scanned)
  // Nodes come from TBB's scalable allocator: GlobalFusion creates them on several threads and
  // the encoder frees them on others; with glibc's arenas, a node made on a helper thread and
  // freed on another cost the encoding twice as long.
  static void* operator new(std::size_t size) {
    if (void* p = scalable_malloc(size)) return p;
    throw std::bad_alloc();
  }
  static void operator delete(void* p) noexcept { scalable_free(p); }
#endif
  /// Deletes child `i` (a leaf, or emptied), as OcTreeBaseImpl::deleteNodeChild but leaving the
  /// tree's node count to SumTree::account().
  void delete_child(unsigned i) {
    delete static_cast<SumNode*>(children[i]);
    children[i] = nullptr;
  }
};

constexpr double kLogOddsQuantum = 4096.0;  ///< log-odds steps per unit (1/4096 resolution)
constexpr int kCountBits = 16;              ///< low bits of a packed sum: contributions

/// The packed contribution of one robot's evidence `log_odds` (0: none).
inline std::int64_t pack_evidence(float log_odds) {
  const auto q = static_cast<std::int64_t>(std::llround(static_cast<double>(log_odds) * kLogOddsQuantum));
  return q == 0 ? 0 : q * (std::int64_t{1} << kCountBits) + 1;
}

/// The summed log-odds of a packed value (not clamped).
inline double unpack_sum(std::int64_t packed) {
  const std::int64_t count = packed & ((std::int64_t{1} << kCountBits) - 1);
  return static_cast<double>((packed - count) / (std::int64_t{1} << kCountBits)) / kLogOddsQuantum;
}

class SumTree : public octomap::OcTreeBase<SumNode> {
 public:
  explicit SumTree(double resolution) : octomap::OcTreeBase<SumNode>(resolution) {}

  /// The encoder keeps the bytes of the subtrees at this depth (2^(16 - kBlockDepth) voxels a
  /// side: 1.6 m at 5 cm) and writes again only those whose sums changed.
  static constexpr unsigned kBlockDepth = kPatchBlockDepth;  ///< patches name these blocks
  /// The block (subtree at kBlockDepth) holding `key`.
  static std::uint64_t block_of(const octomap::OcTreeKey& key) { return patch_block_of(key); }
  /// Whether any voxel of `block` changed since the last forget_changes().
  bool changed(std::uint64_t block) const;
  /// Every block changed() is true for, if they are known and at most `max` (else nullopt: too
  /// many, or everything counts as changed).
  std::optional<std::vector<std::uint64_t>> changed_blocks(std::size_t max) const;
  void forget_changes();

  /// Adds `delta` to every voxel of the aligned block of 2^level voxels per side holding `key`.
  void add(const octomap::OcTreeKey& key, unsigned level, std::int64_t delta);

  /// Adds into one block on one thread, while other writers add into other blocks: the nodes
  /// above the blocks exist already (prepare_block()) and are only read; the writer's nodes are
  /// counted by it (account_writer()) and its changes noted by the caller (note_block()).
  class BlockWriter;
  /// Makes the node at kBlockDepth holding `block` exist (creating its path, expanding uniform
  /// blocks above it), so BlockWriters can add below it at once. Not thread-safe.
  void prepare_block(std::uint64_t block);
  /// Adds a writer's node count to the tree's size once its thread is done. Not thread-safe.
  void account_writer(const BlockWriter& writer);
  /// Notes that voxels of `block` changed (for changed() and the encoder). Not thread-safe.
  void note_block(std::uint64_t block) { note_change(patch_block_key(block), 0); }
  SumNode* root_node() { return root; }
  const SumNode* root_node() const { return root; }
  /// Deletes child `i` of `parent` with its whole subtree.
  void drop_child(SumNode* parent, unsigned i);
  /// As drop_child() and pruneNode(), but counting the nodes deleted into `deleted` instead of
  /// the tree's size: writers may run on disjoint subtrees at once. account() adds them up.
  void drop_child(SumNode* parent, unsigned i, std::size_t& deleted);
  bool prune(SumNode* node, std::size_t& deleted);
  void account(std::size_t deleted) {
    tree_size -= deleted;
    size_changed = true;
    cursor_.depth = 0;
  }
  /// Deletes everything.
  void drop_all();
  /// Forgets the cached descent (call before changing the structure other than by add()).
  void forget_path() { cursor_.depth = 0; }

 private:
  /// One adder's last descent (its nodes by depth, shared by the next one as far as the keys
  /// agree) and the nodes it created, not yet in tree_size.
  struct Cursor {
    std::array<SumNode*, 17> path{};
    octomap::OcTreeKey key;
    unsigned depth = 0;
    std::size_t created = 0;
  };
  SumNode* descend(Cursor& cursor, const octomap::OcTreeKey& key, unsigned depth, bool& fresh);
  static SumNode* new_child(Cursor& cursor, SumNode* node, unsigned i, std::int64_t value);
  static void add_subtree(Cursor& cursor, SumNode* node, std::int64_t delta);
  void add_at(Cursor& cursor, const octomap::OcTreeKey& key, unsigned level, std::int64_t delta);
  /// Puts a cursor's created nodes into tree_size.
  void count_created(Cursor& cursor);

  void note_change(const octomap::OcTreeKey& key, unsigned level);

  Cursor cursor_;  ///< add()'s
  std::unordered_set<std::uint64_t> changed_blocks_;  ///< blocks touched by add()
  std::unordered_set<std::uint64_t> changed_regions_;  ///< adds of more than a block (level, key >> level)
  std::uint32_t region_levels_ = 0;  ///< bit per level that changed_regions_ holds
  bool all_changed_ = true;          ///< nothing encoded yet, or everything dropped
  std::uint64_t last_block_ = ~std::uint64_t{0};  ///< the block noted last (adds come in runs)
};

class SumTree::BlockWriter {
 public:
  explicit BlockWriter(SumTree& tree) : tree_(tree) {}
  /// SumTree::add() for an aligned block inside a prepared block (level <= its level).
  void add(const octomap::OcTreeKey& key, unsigned level, std::int64_t delta) {
    tree_.add_at(cursor_, key, level, delta);
  }

 private:
  friend class SumTree;
  SumTree& tree_;
  Cursor cursor_;
};

/// The encoder's bytes of one block (BodyWriter's output for that subtree), its maximum-
/// likelihood state (0 unknown, 1 free, 2 occupied, 3 mixed) and the nodes it wrote.
struct EncodedBlock {
  std::vector<std::uint8_t> bytes;
  std::uint8_t state = 0;
  std::size_t nodes = 0;
};
/// The blocks of the last encoding, by SumTree::block_of().
struct EncodedBlocks {
  std::unordered_map<std::uint64_t, EncodedBlock> blocks;
};

}  // namespace mapmerge::detail
