#pragma once
/// A received map kept as the bytes it came in, decoded to an octree only when something needs
/// one.
///
/// A robot's update is most often only fused by difference (GlobalFusion reads that off the
/// binary bodies of the old and the new map) and published: building its OcTree (~100 ms and
/// ~57 B of RAM per node for a Freiburg-size map, ~60x the payload) is not needed for that, nor
/// to prepare the map for alignment (for_each_leaf() reads its leaves off the body), nor to fuse
/// a whole map. The same holds for a full (`.ot`) body: its leaves' log-odds are read off it.

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <vector>

#include <Eigen/Core>
#include <octomap/OcTree.h>

#include "mapmerge/map/leaf_set.hpp"

namespace mapmerge {

/// One leaf of a map's binary body, placed as the octree read from that body places it.
struct BodyLeaf {
  bool occupied = false;    ///< else free (OcTree::isNodeOccupied: log-odds >= 0)
  float log_odds = 0.0F;    ///< the leaf's (a binary body's: the clamping bound its state stands for)
  unsigned depth = 0;       ///< 1..16 (16: one voxel)
  Eigen::Vector3f centre;   ///< OcTree::keyToCoord of the leaf at its depth [m]
  double size = 0.0;        ///< OcTree::getNodeSize(depth) [m]
};

class HeldMap;

namespace detail {
/// A HeldMap over a binary body that passed decode's pre-pass (internal to the codec: only bytes
/// so checked may be built into a tree).
std::shared_ptr<const HeldMap> held_checked_body(double resolution,
                                                 std::shared_ptr<const std::vector<std::uint8_t>> body,
                                                 std::size_t num_nodes);
/// The same over a full (`.ot`) body that passed the pre-pass (scan_full_body).
std::shared_ptr<const HeldMap> held_checked_full_body(double resolution,
                                                      std::shared_ptr<const std::vector<std::uint8_t>> body,
                                                      std::size_t num_nodes);
}  // namespace detail

/// An immutable map: an OcTree, its validated binary body (OcTree::writeBinaryData's bytes) or
/// full body (OcTree::writeData's: log-odds kept), or a tree and its binary body. tree() builds
/// the octree from the body on first use and keeps it until release_tree(); safe to call from
/// several threads.
class HeldMap {
 public:
  /// A decoded map, with the binary body it was read from when known (null for `.ot` bodies).
  explicit HeldMap(std::shared_ptr<const octomap::OcTree> tree,
                   std::shared_ptr<const std::vector<std::uint8_t>> binary_body = nullptr);

  double resolution() const { return resolution_; }
  std::size_t num_nodes() const { return num_nodes_; }  ///< inner + leaves
  /// The validated binary body (null for a map decoded from a full `.ot` body).
  const std::shared_ptr<const std::vector<std::uint8_t>>& binary_body() const { return body_; }
  /// The validated full body (OcTree::writeData's bytes) of a map read from one without its tree
  /// (a `.ot` file or a full ROS 2 body); null otherwise.
  const std::shared_ptr<const std::vector<std::uint8_t>>& full_body() const { return full_body_; }
  /// Whether the map's leaves can be read off bytes (a binary or a full body).
  bool has_body() const { return body_ != nullptr || full_body_ != nullptr; }
  /// Log-odds a free and an occupied leaf of the body stand for (the tree's clamping bounds).
  float free_log_odds() const { return free_log_odds_; }
  float occupied_log_odds() const { return occupied_log_odds_; }

  /// The octree, built from the body on the first call (O(nodes)); never null.
  std::shared_ptr<const octomap::OcTree> tree() const;
  /// Whether tree() has been built (a test of laziness; the answer may be stale at once).
  bool has_tree() const;
  /// Lets go of the octree built from the body (~57 B a node); the next tree() builds it again,
  /// and whoever holds the old one keeps it. A map without a body keeps its tree. Returns
  /// whether a tree was let go of. The map's content is unchanged: it stays the same map.
  bool release_tree() const;
  /// The map's occupied leaves, read off the body on the first call (the tree is not built) and
  /// kept: what an overlap estimate asks of a map, at ~8 B per occupied leaf.
  std::shared_ptr<const LeafSet> occupied_leaves() const;
  /// Calls `leaf` for every leaf of the body (its tree is not built), depth first in child
  /// order: the order, centres, sizes and log-odds of a walk of tree(). False (nothing visited)
  /// for a map without a body.
  bool for_each_leaf(const std::function<void(const BodyLeaf&)>& leaf) const;

 private:
  friend std::shared_ptr<const HeldMap> detail::held_checked_body(double, std::shared_ptr<const std::vector<std::uint8_t>>,
                                                                  std::size_t);
  friend std::shared_ptr<const HeldMap> detail::held_checked_full_body(
      double, std::shared_ptr<const std::vector<std::uint8_t>>, std::size_t);
  HeldMap(double resolution, std::shared_ptr<const std::vector<std::uint8_t>> body, std::size_t num_nodes,
          bool binary);

  double resolution_;
  std::size_t num_nodes_;
  std::shared_ptr<const std::vector<std::uint8_t>> body_;       ///< binary
  std::shared_ptr<const std::vector<std::uint8_t>> full_body_;  ///< full (`.ot`)
  float free_log_odds_;
  float occupied_log_odds_;
  mutable std::mutex tree_mutex_;  ///< guards tree_ (held while a tree is built)
  mutable std::shared_ptr<const octomap::OcTree> tree_;
  mutable std::atomic<bool> built_flag_{false};
  mutable std::once_flag occupied_once_;
  mutable std::shared_ptr<const LeafSet> occupied_;
};

}  // namespace mapmerge
