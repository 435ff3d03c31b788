#include "mapmerge/map/held_map.hpp"

#include "codec_detail.hpp"
#include "mapmerge/map/map_io.hpp"

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

bool HeldMap::has_tree() const { return built_flag_.load(std::memory_order_acquire); }

}  // namespace mapmerge
