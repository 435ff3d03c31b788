#pragma once
/// Adds log-odds to aligned blocks of an OcTree in place (internal to mapmerge_core).

#include <array>

#include <octomap/OcTree.h>

namespace mapmerge::detail {

/// Adds evidence to a tree without OctoMap's per-voxel recursion: a cached root-to-leaf path
/// makes neighbouring updates cheap, and a whole aligned block (2^level voxels per side) is
/// updated at its own depth. Inner nodes are left stale: call updateInnerOccupancy() afterwards.
class TreeWriter {
 public:
  explicit TreeWriter(octomap::OcTree& tree);

  /// Adds `delta` (clamped to the tree's thresholds) to every voxel of the aligned block of
  /// 2^level voxels per side that holds `key`. Unknown voxels start from log-odds 0.
  void add(const octomap::OcTreeKey& key, unsigned level, float delta);

 private:
  octomap::OcTreeNode* descend(const octomap::OcTreeKey& key, unsigned depth, bool& fresh);
  void add_subtree(octomap::OcTreeNode* node, float delta);
  float clamp(float value) const;

  octomap::OcTree& tree_;
  float min_log_odds_;
  float max_log_odds_;
  std::array<octomap::OcTreeNode*, 17> path_{};  ///< nodes of the last descent, by depth
  octomap::OcTreeKey path_key_;
  unsigned path_depth_ = 0;  ///< deepest valid entry of path_ (0: only the root)
};

}  // namespace mapmerge::detail
