#pragma once
/// What OctoMap keeps protected, for code that builds trees node by node (internal to
/// mapmerge_core): pointers to protected members, formed through derived classes as the language
/// allows. OctoMap creates a root only inside updateNode() and keeps a node's emptied child array.

#include <octomap/OcTree.h>

namespace mapmerge::detail {

constexpr unsigned kTreeDepth = 16;  ///< OctoMap's fixed number of levels below the root

template <class Node>
struct NodeInternals : Node {
  static constexpr auto kChildren = &NodeInternals::children;
};

struct OcTreeInternals : octomap::OcTree {
  static constexpr auto kRoot = &OcTreeInternals::root;
  static constexpr auto kTreeSize = &OcTreeInternals::tree_size;
  static constexpr auto kSizeChanged = &OcTreeInternals::size_changed;
};

/// Frees the child pointer array of a node whose children are all gone, so that it is a leaf
/// again (OctoMap's deleteNodeChild keeps the array). Any of OctoMap's node types.
template <class Node>
void free_children_array(Node* node) {
  auto& children = node->*NodeInternals<Node>::kChildren;
  delete[] children;
  children = nullptr;
}

/// Creates the root of an empty `tree` (log-odds 0), counted in the tree's size.
inline octomap::OcTreeNode* create_root(octomap::OcTree& tree) {
  octomap::OcTreeBaseImpl<octomap::OcTreeNode, octomap::AbstractOccupancyOcTree>& base = tree;
  auto* root = new octomap::OcTreeNode();
  base.*OcTreeInternals::kRoot = root;
  ++(base.*OcTreeInternals::kTreeSize);
  base.*OcTreeInternals::kSizeChanged = true;
  return root;
}

}  // namespace mapmerge::detail
