#include "tree_writer.hpp"

#include <algorithm>

#include "octree_internals.hpp"

namespace mapmerge::detail {

TreeWriter::TreeWriter(octomap::OcTree& tree)
    : tree_(tree),
      min_log_odds_(tree.getClampingThresMinLog()),
      max_log_odds_(tree.getClampingThresMaxLog()) {}

float TreeWriter::clamp(float value) const {
  return std::min(max_log_odds_, std::max(min_log_odds_, value));
}

octomap::OcTreeNode* TreeWriter::descend(const octomap::OcTreeKey& key, unsigned depth,
                                         bool& fresh) {
  octomap::OcTreeNode* root = tree_.getRoot();
  fresh = false;
  if (root == nullptr) {
    root = create_root(tree_);
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
  octomap::OcTreeNode* node = path_[d];
  for (unsigned level = d; level < depth; ++level) {
    const unsigned pos = octomap::computeChildIdx(key, static_cast<int>(kTreeDepth - 1 - level));
    if (tree_.nodeChildExists(node, pos)) {
      node = tree_.getNodeChild(node, pos);
    } else if (!fresh && !tree_.nodeHasChildren(node)) {
      tree_.expandNode(node);  // a pruned leaf: its children inherit its value
      node = tree_.getNodeChild(node, pos);
    } else {
      node = tree_.createNodeChild(node, pos);  // unknown space: log-odds 0
      fresh = true;
    }
    path_[level + 1] = node;
  }
  path_key_ = key;
  path_depth_ = depth;
  return node;
}

void TreeWriter::add_subtree(octomap::OcTreeNode* node, float delta) {
  if (!tree_.nodeHasChildren(node)) {
    node->setLogOdds(clamp(node->getLogOdds() + delta));
    return;
  }
  for (unsigned i = 0; i < 8; ++i) {
    if (tree_.nodeChildExists(node, i)) {
      add_subtree(tree_.getNodeChild(node, i), delta);  // depth <= 16: bounded recursion
    } else {
      tree_.createNodeChild(node, i)->setLogOdds(clamp(delta));
    }
  }
}

void TreeWriter::add(const octomap::OcTreeKey& key, unsigned level, float delta) {
  bool fresh = false;
  octomap::OcTreeNode* node = descend(key, kTreeDepth - level, fresh);
  if (fresh) {
    node->setLogOdds(clamp(delta));
  } else {
    add_subtree(node, delta);
  }
}

}  // namespace mapmerge::detail
