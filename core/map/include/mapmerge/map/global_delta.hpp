#pragma once
/// A change of the global map sent as the blocks that changed, not as the whole map.
///
/// The global map's `.bt` body is a pre-order list of node records; the subtree of each block
/// (2^5 voxels a side, at depth 11 of the 16-level tree: 1.6 m at 5 cm) is a contiguous run of
/// records. GlobalFusion::encode() knows which blocks it wrote again; a receiver holding the
/// previous version's decoded tree puts just those blocks into it (apply_block_patches), which
/// costs O(changed blocks), where decoding a Freiburg-size global map costs ~100 ms and freeing
/// the old one as much again. The patched tree is node for node the tree decode_map() builds
/// from the new version's `.bt`: same structure, same log-odds.

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include <octomap/OcTree.h>

namespace mapmerge {

/// Depth of a block's root in the octree (blocks are 2^(16 - kPatchBlockDepth) voxels a side).
constexpr unsigned kPatchBlockDepth = 11;

/// What a block holds once its voxels are read by maximum likelihood.
enum class BlockState : std::uint8_t { kUnknown = 0, kFree = 1, kOccupied = 2, kMixed = 3 };

/// One block of the new version of a map.
struct BlockPatch {
  /// The block: its voxels' keys shifted right by 16 - kPatchBlockDepth, per axis, packed
  /// x | y << 16 | z << 32.
  std::uint64_t block = 0;
  BlockState state = BlockState::kUnknown;
  /// kMixed: the block's records as in a `.bt` body (its root's record first, pre-order);
  /// empty otherwise.
  std::vector<std::uint8_t> records;
};

/// The block holding `key`, as BlockPatch::block names it.
inline std::uint64_t patch_block_of(const octomap::OcTreeKey& key) {
  constexpr unsigned s = 16 - kPatchBlockDepth;
  return std::uint64_t{key[0]} >> s | (std::uint64_t{key[1]} >> s) << 16 | (std::uint64_t{key[2]} >> s) << 32;
}

/// The first voxel key of `block` (the inverse of patch_block_of() on a block's corner).
inline octomap::OcTreeKey patch_block_key(std::uint64_t block) {
  constexpr unsigned s = 16 - kPatchBlockDepth;
  return octomap::OcTreeKey(static_cast<octomap::key_type>((block & 0xFFFFU) << s),
                            static_cast<octomap::key_type>(((block >> 16) & 0xFFFFU) << s),
                            static_cast<octomap::key_type>(((block >> 32) & 0xFFFFU) << s));
}

/// 64-bit FNV-1a of `size` bytes: names a global map's payload, so a receiver patches only the
/// exact map a patch was made from (GlobalMapDelta's base_hash and hash).
std::uint64_t payload_hash(const std::uint8_t* data, std::size_t size);
inline std::uint64_t payload_hash(const std::vector<std::uint8_t>& data) { return payload_hash(data.data(), data.size()); }

/// Why `patches` cannot be applied (empty when they can): a block id out of the key space or
/// named twice, an unknown state, records on a uniform block, or records that are not exactly
/// one well-formed subtree of a block (every byte consumed, no deeper than the tree, no empty
/// record). At most `max_nodes` nodes in all. O(bytes). Never trusts its input.
std::string check_block_patches(const std::vector<BlockPatch>& patches, std::size_t max_nodes);

/// Puts checked patches (check_block_patches) into `tree`, a tree decode_map() built from the
/// previous version's `.bt` (or one patched from it): afterwards it is the tree decode_map()
/// builds from the new version. O(patched blocks * tree depth + their records).
void apply_block_patches(octomap::OcTree& tree, const std::vector<BlockPatch>& patches);

}  // namespace mapmerge
