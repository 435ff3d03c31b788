#include "mapmerge/map/leaf_set.hpp"

#include <algorithm>
#include <cmath>

#include <Eigen/Geometry>
#include <octomap/OcTree.h>

#include "mapmerge/map/held_map.hpp"
#include "morton.hpp"
#include "octree_internals.hpp"
#include "body_leaves.hpp"

namespace mapmerge {
namespace {

using detail::kTreeDepth;
constexpr std::int64_t kCentreKey = 1 << (kTreeDepth - 1);  ///< key of the cell at the origin

using detail::morton_code;  // a depth-first walk meets the leaves of one depth in increasing order
using detail::morton_compact;

/// The code of the corner of the leaf `depth` levels below the root holding the key `code`.
std::uint64_t mask_to_depth(std::uint64_t code, unsigned depth) {
  return code & ~((std::uint64_t{1} << (3 * (kTreeDepth - depth))) - 1);
}

}  // namespace

void LeafSet::add(unsigned depth, std::uint32_t x, std::uint32_t y, std::uint32_t z) {
  by_depth_[depth].push_back(morton_code(x, y, z));
}

void LeafSet::finish() {
  size_ = 0;
  for (auto& keys : by_depth_) {
    if (!std::is_sorted(keys.begin(), keys.end())) std::sort(keys.begin(), keys.end());  // depth first: sorted
    keys.shrink_to_fit();
    size_ += keys.size();
  }
}

LeafSet LeafSet::of(const HeldMap& map, LeafState state) {
  if (!map.has_body()) return of(*map.tree(), state);
  LeafSet out;
  out.resolution_ = map.resolution();
  const bool wanted = state == LeafState::kOccupied;
  detail::for_each_body_leaf(map, [&](float, bool occupied, unsigned depth, std::uint32_t x, std::uint32_t y,
                                      std::uint32_t z) {
    if (occupied == wanted) out.add(depth, x, y, z);
  });
  out.finish();
  return out;
}

LeafSet LeafSet::of(const octomap::OcTree& tree, LeafState state) {
  LeafSet out;
  out.resolution_ = tree.getResolution();
  const bool occupied = state == LeafState::kOccupied;
  for (auto it = tree.begin_leafs(), end = tree.end_leafs(); it != end; ++it) {
    if (tree.isNodeOccupied(*it) != occupied) continue;
    const unsigned depth = it.getDepth();
    const octomap::OcTreeKey k = it.getKey();
    out.by_depth_[depth].push_back(mask_to_depth(morton_code(k[0], k[1], k[2]), depth));
  }
  out.finish();
  return out;
}

bool LeafSet::contains(const Eigen::Vector3d& p) const {
  std::uint64_t key[3];
  for (int a = 0; a < 3; ++a) {
    const double k = std::floor(p[a] / resolution_) + static_cast<double>(kCentreKey);
    if (!(k >= 0.0 && k < static_cast<double>(1U << kTreeDepth))) return false;
    key[a] = static_cast<std::uint64_t>(k);
  }
  const std::uint64_t packed = morton_code(key[0], key[1], key[2]);
  for (unsigned d = 0; d < kLevels; ++d) {
    const auto& keys = by_depth_[d];
    if (!keys.empty() && std::binary_search(keys.begin(), keys.end(), mask_to_depth(packed, d))) return true;
  }
  return false;
}

Eigen::Vector3d LeafSet::centre(std::size_t i) const {
  unsigned d = 0;
  while (i >= by_depth_[d].size()) i -= by_depth_[d++].size();  // i < size(): ends below kLevels
  const std::uint64_t k = by_depth_[d][i];
  const double half = static_cast<double>((1U << kTreeDepth) >> d) / 2.0;
  Eigen::Vector3d c;
  for (int a = 0; a < 3; ++a) {
    const auto key = static_cast<double>(morton_compact(k >> a));
    c[a] = (key - static_cast<double>(kCentreKey) + half) * resolution_;
  }
  return c;
}

double estimate_overlap(const LeafSet& target, const LeafSet& source,
                        const Eigen::Matrix4d& T_target_source, std::size_t samples) {
  if (target.size() == 0 || source.size() == 0) return 0.0;
  const std::size_t stride = std::max<std::size_t>(1, source.size() / std::max<std::size_t>(1, samples));
  const double r = target.resolution();
  std::size_t seen = 0, hit = 0;
  for (std::size_t i = 0; i < source.size(); i += stride) {
    const Eigen::Vector3d p = (T_target_source * source.centre(i).homogeneous()).head<3>();
    ++seen;
    bool found = false;  // an occupied target voxel within one voxel
    for (int dx = -1; dx <= 1 && !found; ++dx)
      for (int dy = -1; dy <= 1 && !found; ++dy)
        for (int dz = -1; dz <= 1 && !found; ++dz) found = target.contains(p + Eigen::Vector3d(dx, dy, dz) * r);
    hit += found ? 1 : 0;
  }
  return static_cast<double>(hit) / static_cast<double>(seen);
}

}  // namespace mapmerge
