#include "mapmerge/map/map_io.hpp"

#include <fstream>
#include <sstream>

#include <octomap/AbstractOcTree.h>

namespace mapmerge {
namespace {

bool ends_with(const std::string& s, const std::string& suffix) {
  return s.size() >= suffix.size() && s.compare(s.size() - suffix.size(), suffix.size(), suffix) == 0;
}

}  // namespace

std::unique_ptr<octomap::OcTree> read_octree_file(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw MapError("cannot open map file '" + path + "'");
  if (ends_with(path, ".bt")) {
    auto tree = std::make_unique<octomap::OcTree>(0.1);
    if (!tree->readBinary(in)) throw MapError("'" + path + "' is not a binary OctoMap (.bt)");
    return tree;
  }
  if (ends_with(path, ".ot")) {
    std::unique_ptr<octomap::AbstractOcTree> abstract(octomap::AbstractOcTree::read(in));
    auto* tree = dynamic_cast<octomap::OcTree*>(abstract.get());
    if (tree == nullptr) throw MapError("'" + path + "' is not a full OcTree (.ot)");
    abstract.release();
    return std::unique_ptr<octomap::OcTree>(tree);
  }
  throw MapError("'" + path + "': unsupported map format (expected .bt or .ot)");
}

void write_octree_file(const octomap::OcTree& tree, const std::string& path) {
  std::ofstream out(path, std::ios::binary);
  if (!out || !tree.writeBinaryConst(out)) throw MapError("cannot write map file '" + path + "'");
}

}  // namespace mapmerge
