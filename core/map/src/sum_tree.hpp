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
#include <utility>
#include <vector>

#include <octomap/OcTreeBase.h>
#include <octomap/OcTreeDataNode.h>

#include "mapmerge/map/global_delta.hpp"

namespace mapmerge::detail {

/// A voxel's packed sum (0 when created: no evidence).
class SumNode : public octomap::OcTreeDataNode<std::int64_t> {
 public:
  SumNode() : octomap::OcTreeDataNode<std::int64_t>(0) {}
  explicit SumNode(std::int64_t value) : octomap::OcTreeDataNode<std::int64_t>(value) {}
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
    path_depth_ = 0;
  }
  /// Deletes everything.
  void drop_all();
  /// Forgets the cached descent (call before changing the structure other than by add()).
  void forget_path() { path_depth_ = 0; }

 private:
  SumNode* descend(const octomap::OcTreeKey& key, unsigned depth, bool& fresh);
  SumNode* new_child(SumNode* node, unsigned i, std::int64_t value);
  void add_subtree(SumNode* node, std::int64_t delta);

  void note_change(const octomap::OcTreeKey& key, unsigned level);

  std::array<SumNode*, 17> path_{};  ///< nodes of the last descent, by depth
  std::unordered_set<std::uint64_t> changed_blocks_;  ///< blocks touched by add()
  std::unordered_set<std::uint64_t> changed_regions_;  ///< adds of more than a block (level, key >> level)
  std::uint32_t region_levels_ = 0;  ///< bit per level that changed_regions_ holds
  bool all_changed_ = true;          ///< nothing encoded yet, or everything dropped
  std::uint64_t last_block_ = ~std::uint64_t{0};  ///< the block noted last (adds come in runs)
  octomap::OcTreeKey path_key_;
  unsigned path_depth_ = 0;
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
