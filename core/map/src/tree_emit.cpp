#include <sstream>
#include <utility>

#include "tree_scan.hpp"

namespace mapmerge::detail {

void append_binary_body(const octomap::OcTree& tree, std::vector<std::uint8_t>& out) {
  const octomap::OcTreeNode* root = tree.getRoot();
  if (root == nullptr) return;
  // Pre-order, children in index order: a stack holding each node's inner children reversed.
  std::vector<const octomap::OcTreeNode*> stack{root};
  stack.reserve(16 * 8 + 1);
  while (!stack.empty()) {
    const octomap::OcTreeNode* node = stack.back();
    stack.pop_back();
    std::uint8_t bytes[2] = {0, 0};
    const octomap::OcTreeNode* inner[8];
    int n_inner = 0;
    for (unsigned i = 0; i < 8; ++i) {
      if (!tree.nodeChildExists(node, i)) continue;  // 00: unknown
      const octomap::OcTreeNode* child = tree.getNodeChild(node, i);
      unsigned code = 1;  // 01 (bit 2i): free leaf
      if (tree.nodeHasChildren(child)) {
        code = 3;  // 11: inner node, its own record follows
        inner[n_inner++] = child;
      } else if (tree.isNodeOccupied(child)) {
        code = 2;  // 10 (bit 2i+1): occupied leaf
      }
      bytes[i / 4] = static_cast<std::uint8_t>(bytes[i / 4] | (code << (2 * (i % 4))));
    }
    out.push_back(bytes[0]);
    out.push_back(bytes[1]);
    while (n_inner > 0) stack.push_back(inner[--n_inner]);
  }
}

void append_binary_header(const octomap::OcTree& tree, std::vector<std::uint8_t>& out) {
  std::ostringstream header;  // default stream formatting, as OctoMap's writer
  header << "# Octomap OcTree binary file\n"
            "# (feel free to add / change comments, but leave the first line as it is!)\n#\n"
         << "id " << tree.getTreeType() << "\n"
         << "size " << tree.size() << "\n"
         << "res " << tree.getResolution() << "\n"
         << "data\n";
  const std::string text = header.str();
  out.insert(out.end(), text.begin(), text.end());
}

}  // namespace mapmerge::detail
