#include "mapmerge/map/held_map.hpp"

#include <cmath>

#include "codec_detail.hpp"
#include "mapmerge/map/map_io.hpp"
#include "tree_scan.hpp"

namespace mapmerge {
namespace {

/// The clamping bounds of a tree read from a binary body: OctoMap's defaults.
const octomap::OcTree& default_tree() {
  static const octomap::OcTree tree(0.1);
  return tree;
}

}  // namespace

namespace detail {

std::shared_ptr<const HeldMap> held_checked_body(double resolution,
                                                 std::shared_ptr<const std::vector<std::uint8_t>> body,
                                                 std::size_t num_nodes) {
  return std::shared_ptr<const HeldMap>(new HeldMap(resolution, std::move(body), num_nodes));
}

}  // namespace detail

HeldMap::HeldMap(std::shared_ptr<const octomap::OcTree> tree, std::shared_ptr<const std::vector<std::uint8_t>> binary_body)
    : resolution_(tree ? tree->getResolution() : 0.0),
      num_nodes_(tree ? tree->size() : 0),
      body_(std::move(binary_body)),
      free_log_odds_(tree ? tree->getClampingThresMinLog() : 0.0F),
      occupied_log_odds_(tree ? tree->getClampingThresMaxLog() : 0.0F),
      tree_(std::move(tree)) {
  if (!tree_) throw MapError("HeldMap: null tree");
  built_flag_.store(true, std::memory_order_release);  // tree() never builds
}

HeldMap::HeldMap(double resolution, std::shared_ptr<const std::vector<std::uint8_t>> body, std::size_t num_nodes)
    : resolution_(resolution),
      num_nodes_(num_nodes),
      body_(std::move(body)),
      free_log_odds_(default_tree().getClampingThresMinLog()),
      occupied_log_odds_(default_tree().getClampingThresMaxLog()) {}

std::shared_ptr<const octomap::OcTree> HeldMap::tree() const {
  std::lock_guard<std::mutex> lock(tree_mutex_);
  if (!tree_) {
    tree_ = detail::build_checked_binary_tree(resolution_, *body_);
    built_flag_.store(true, std::memory_order_release);
  }
  return tree_;
}

bool HeldMap::release_tree() const {
  std::shared_ptr<const octomap::OcTree> old;  // freed after the lock is let go of
  std::lock_guard<std::mutex> lock(tree_mutex_);
  if (!body_ || !tree_) return false;
  old = std::move(tree_);
  built_flag_.store(false, std::memory_order_release);
  return true;
}

std::shared_ptr<const LeafSet> HeldMap::occupied_leaves() const {
  std::call_once(occupied_once_,
                 [this] { occupied_ = std::make_shared<const LeafSet>(LeafSet::of(*this, LeafState::kOccupied)); });
  return occupied_;
}

bool HeldMap::for_each_leaf(const std::function<void(const BodyLeaf&)>& leaf) const {
  if (!body_) return false;
  // OcTree::keyToCoord(key, depth) and getNodeSize(depth), in the same arithmetic (so the same
  // floats): (floor((key - centre) / 2^(16 - depth)) + 0.5) * size, or (key - centre + 0.5) * res
  // at depth 16; a leaf's lowest-corner key makes the floor exact.
  constexpr int kCentre = 1 << (detail::kTreeDepth - 1);
  BodyLeaf b;
  detail::for_each_binary_leaf(*body_, [&](unsigned code, unsigned depth, std::uint32_t x, std::uint32_t y,
                                           std::uint32_t z) {
    b.occupied = code == 2;
    b.depth = depth;
    const std::uint32_t key[3] = {x, y, z};
    if (depth == detail::kTreeDepth) {
      b.size = resolution_;
      for (int a = 0; a < 3; ++a) {
        b.centre[a] = static_cast<float>((static_cast<double>(static_cast<int>(key[a]) - kCentre) + 0.5) * resolution_);
      }
    } else {
      const double cells = static_cast<double>(1U << (detail::kTreeDepth - depth));
      b.size = resolution_ * cells;
      for (int a = 0; a < 3; ++a) {
        b.centre[a] = static_cast<float>(
            (std::floor((static_cast<double>(key[a]) - static_cast<double>(kCentre)) / cells) + 0.5) * b.size);
      }
    }
    leaf(b);
  });
  return true;
}

bool HeldMap::has_tree() const { return built_flag_.load(std::memory_order_acquire); }

}  // namespace mapmerge
