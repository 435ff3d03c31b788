#include "mapmerge/map/held_map.hpp"

#include <cmath>

#include "codec_detail.hpp"
#include "mapmerge/map/map_io.hpp"
#include "body_leaves.hpp"

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
  return std::shared_ptr<const HeldMap>(new HeldMap(resolution, std::move(body), num_nodes, true));
}

std::shared_ptr<const HeldMap> held_checked_full_body(double resolution,
                                                      std::shared_ptr<const std::vector<std::uint8_t>> body,
                                                      std::size_t num_nodes) {
  return std::shared_ptr<const HeldMap>(new HeldMap(resolution, std::move(body), num_nodes, false));
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

HeldMap::HeldMap(double resolution, std::shared_ptr<const std::vector<std::uint8_t>> body, std::size_t num_nodes,
                 bool binary)
    : resolution_(resolution),
      num_nodes_(num_nodes),
      body_(binary ? std::move(body) : nullptr),
      full_body_(binary ? nullptr : std::move(body)),
      free_log_odds_(default_tree().getClampingThresMinLog()),
      occupied_log_odds_(default_tree().getClampingThresMaxLog()) {}

std::shared_ptr<const octomap::OcTree> HeldMap::tree() const {
  std::lock_guard<std::mutex> lock(tree_mutex_);
  if (!tree_) {
    tree_ = body_ ? detail::build_checked_binary_tree(resolution_, *body_)
                  : detail::build_checked_full_tree(resolution_, *full_body_);
    built_flag_.store(true, std::memory_order_release);
  }
  return tree_;
}

bool HeldMap::release_tree() const {
  std::shared_ptr<const octomap::OcTree> old;  // freed after the lock is let go of
  std::lock_guard<std::mutex> lock(tree_mutex_);
  if (!has_body() || !tree_) return false;
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
  BodyLeaf b;
  return detail::for_each_body_leaf(*this, [&](float log_odds, bool occupied, unsigned depth, std::uint32_t x,
                                               std::uint32_t y, std::uint32_t z) {
    b.occupied = occupied;
    b.log_odds = log_odds;
    b.depth = depth;
    b.size = detail::leaf_size(depth, resolution_);
    b.centre = Eigen::Vector3f(static_cast<float>(detail::leaf_coord(x, depth, resolution_)),
                               static_cast<float>(detail::leaf_coord(y, depth, resolution_)),
                               static_cast<float>(detail::leaf_coord(z, depth, resolution_)));
    leaf(b);
  });
}

bool HeldMap::has_tree() const { return built_flag_.load(std::memory_order_acquire); }

}  // namespace mapmerge
