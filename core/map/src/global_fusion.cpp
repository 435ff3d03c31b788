#include "mapmerge/map/global_fusion.hpp"

#include <algorithm>
#include <cmath>
#include <unordered_map>

#include "leaf_mapper.hpp"
#include "mapmerge/map/map_io.hpp"
#include "sum_tree.hpp"
#include "tree_scan.hpp"

namespace mapmerge {
namespace {

constexpr unsigned kTreeDepth = 16;

/// GlobalFusion's sink: packed evidence added to the sums.
struct SumSink {
  detail::SumTree& sums;
  void apply(const octomap::OcTreeKey& key, unsigned level, std::int64_t delta) {
    sums.add(key, level, delta);
  }
};

/// One robot's packed evidence for a leaf of log-odds `v` (0: ignored, as fuse_into ignores it).
std::int64_t evidence(float v, const FuseConfig& config) {
  return v < 0.0F && !config.fuse_free ? 0 : detail::pack_evidence(v);
}

/// A region of a robot map's frame whose evidence changed, as a cube of the map's grid.
struct ChangedCube {
  Eigen::Vector3d centre;
  double size = 0.0;
  std::int64_t delta = 0;
};

/// One side of the simultaneous walk over two trees: a node, or a uniform value inherited from a
/// leaf above (with `node` null), or nothing (`known` false).
struct Side {
  const octomap::OcTreeNode* node = nullptr;
  bool known = false;
  float value = 0.0F;
};

/// Walks the old and the new map of a robot (same resolution, same frame) together and lists
/// where their evidence differs; sums the new map's fusion work on the way.
class TreeDiff {
 public:
  TreeDiff(const octomap::OcTree& before, const octomap::OcTree& after, double target_res,
           const FuseConfig& config)
      : before_(before), after_(after), target_res_(target_res), config_(config) {}

  void run() {
    Side a{before_.getRoot(), before_.getRoot() != nullptr};
    Side b{after_.getRoot(), after_.getRoot() != nullptr};
    walk(a, b, octomap::OcTreeKey(32768, 32768, 32768), 0);
  }
  std::vector<ChangedCube> cubes;
  double work = 0.0;  ///< fusion work of the new map (FuseConfig::max_work's measure)

 private:
  /// A node without children is a uniform block from here down.
  Side settle(Side s, const octomap::OcTree& tree, unsigned depth, bool count_work) {
    if (s.node == nullptr || tree.nodeHasChildren(s.node)) return s;
    s.value = s.node->getLogOdds();
    s.node = nullptr;
    if (count_work && (s.value >= 0.0F || config_.fuse_free)) {
      work += detail::leaf_fusion_work(std::max(1.0, std::ceil(tree.getNodeSize(depth) / target_res_)));
    }
    return s;
  }

  static Side child(const octomap::OcTree& tree, const Side& s, unsigned i) {
    if (s.node == nullptr) return s;  // nothing, or a uniform block: the same for every child
    if (!tree.nodeChildExists(s.node, i)) return Side{};
    return Side{tree.getNodeChild(s.node, i), true};
  }

  void walk(Side a, Side b, const octomap::OcTreeKey& key, unsigned depth) {
    a = settle(a, before_, depth, false);
    b = settle(b, after_, depth, true);
    if (a.node == nullptr && b.node == nullptr) {
      const std::int64_t ea = a.known ? evidence(a.value, config_) : 0;
      const std::int64_t eb = b.known ? evidence(b.value, config_) : 0;
      if (ea != eb) {
        const double c[3] = {after_.keyToCoord(key[0], depth), after_.keyToCoord(key[1], depth),
                             after_.keyToCoord(key[2], depth)};
        cubes.push_back({Eigen::Vector3d(c[0], c[1], c[2]), after_.getNodeSize(depth), eb - ea});
      }
      return;
    }
    const auto offset = static_cast<octomap::key_type>(32768 >> (depth + 1));
    for (unsigned i = 0; i < 8; ++i) {
      octomap::OcTreeKey k;
      octomap::computeChildKey(i, offset, key, k);
      walk(child(before_, a, i), child(after_, b, i), k, depth + 1);  // depth <= 16
    }
  }

  const octomap::OcTree& before_;
  const octomap::OcTree& after_;
  double target_res_;
  const FuseConfig& config_;
};

/// Packed votes of source leaves finer than the target's voxels: the largest per voxel.
using FineVotes = std::unordered_map<octomap::OcTreeKey, float, octomap::OcTreeKey::KeyHash>;

}  // namespace

GlobalFusion::GlobalFusion(double resolution, const FuseConfig& config)
    : resolution_(resolution), config_(config) {
  if (!(resolution > 0.0) || !std::isfinite(resolution)) {
    throw MapError("GlobalFusion: resolution must be positive");
  }
  sums_ = std::make_unique<detail::SumTree>(resolution);
  encoded_ = std::make_unique<detail::EncodedBlocks>();
}

GlobalFusion::~GlobalFusion() = default;

bool GlobalFusion::empty() const { return robots_.empty(); }

std::vector<std::string> GlobalFusion::robots() const {
  std::vector<std::string> out;
  for (const auto& kv : robots_) out.push_back(kv.first);
  return out;
}

bool GlobalFusion::holds(const std::string& robot, const octomap::OcTree* map,
                         const Eigen::Matrix4d& T) const {
  const auto it = robots_.find(robot);
  return it != robots_.end() && it->second.map.get() == map && it->second.T_global_robot == T;
}

std::optional<Eigen::Matrix4d> GlobalFusion::pose_of(const std::string& robot) const {
  const auto it = robots_.find(robot);
  if (it == robots_.end()) return std::nullopt;
  return it->second.T_global_robot;
}

std::shared_ptr<const octomap::OcTree> GlobalFusion::map_of(const std::string& robot) const {
  const auto it = robots_.find(robot);
  return it == robots_.end() ? nullptr : it->second.map;
}

std::size_t GlobalFusion::memory_usage() const { return sums_->memoryUsage(); }

void GlobalFusion::add_full(const Entry& entry, int sign, GlobalFuseResult& stats) {
  const octomap::OcTree& map = *entry.map;
  const Eigen::Matrix4d& T = entry.T_global_robot;
  FuseResult counts;
  SumSink sink{*sums_};
  detail::LeafMapper<SumSink, std::int64_t> mapper(T, resolution_, sink, counts);
  FineVotes fine;
  for (auto it = map.begin_leafs(), end = map.end_leafs(); it != end; ++it) {
    const float v = it->getLogOdds();
    const std::int64_t e = evidence(v, config_);
    if (e == 0) continue;
    ++stats.cubes;
    const Eigen::Vector3d c(it.getX(), it.getY(), it.getZ());
    if (it.getSize() >= resolution_ * (1 - 1e-9)) {
      mapper.add_cube(c, it.getSize(), sign * e);
      continue;
    }
    const Eigen::Vector3d ct = T.topLeftCorner<3, 3>() * c + T.topRightCorner<3, 1>();
    octomap::OcTreeKey key;
    if (!sums_->coordToKeyChecked(ct.x(), ct.y(), ct.z(), key)) continue;
    auto [vote, inserted] = fine.try_emplace(key, v);
    if (!inserted) vote->second = std::max(vote->second, v);
  }
  for (const auto& [key, v] : fine) sums_->add(key, 0, sign * evidence(v, config_));
  stats.voxel_updates += counts.voxel_updates + fine.size();
  stats.block_updates += counts.block_updates;
}

bool GlobalFusion::add_difference(const Entry& before, const Entry& after, GlobalFuseResult& stats) {
  TreeDiff diff(*before.map, *after.map, resolution_, config_);
  diff.run();
  if (diff.work > config_.max_work) {
    stats.reason = "map would cost ~" + std::to_string(static_cast<long long>(diff.work)) +
                   " voxel visits, more than max_work (huge pruned leaves?)";
    return false;
  }
  FuseResult counts;
  SumSink sink{*sums_};
  detail::LeafMapper<SumSink, std::int64_t> mapper(after.T_global_robot, resolution_, sink, counts);
  for (const ChangedCube& cube : diff.cubes) mapper.add_cube(cube.centre, cube.size, cube.delta);
  stats.cubes += diff.cubes.size();
  stats.voxel_updates += counts.voxel_updates;
  stats.block_updates += counts.block_updates;
  return true;
}

GlobalFuseResult GlobalFusion::set(const std::string& robot,
                                   std::shared_ptr<const octomap::OcTree> map,
                                   const Eigen::Matrix4d& T_global_robot) {
  GlobalFuseResult r;
  r.reason = map ? detail::check_rigid(T_global_robot, config_.rigid_tolerance) : "no map";
  if (!r.reason.empty()) {
    remove(robot);
    return r;
  }
  Entry next{std::move(map), T_global_robot};
  const auto it = robots_.find(robot);
  if (it != robots_.end() && it->second.map == next.map && it->second.T_global_robot == T_global_robot) {
    r.ok = true;
    return r;
  }
  const bool same_grid = it != robots_.end() && it->second.T_global_robot == T_global_robot &&
                         it->second.map->getResolution() == next.map->getResolution() &&
                         next.map->getResolution() >= resolution_ * (1 - 1e-9);
  if (same_grid) {
    r.ok = add_difference(it->second, next, r);
    r.incremental = r.ok;
  } else {
    const double work = detail::estimate_work(*next.map, resolution_, config_.fuse_free);
    r.ok = work <= config_.max_work;
    if (!r.ok) {
      r.reason = "map would cost ~" + std::to_string(static_cast<long long>(work)) +
                 " voxel visits, more than max_work (huge pruned leaves?)";
    } else {
      if (it != robots_.end()) add_full(it->second, -1, r);
      add_full(next, +1, r);
    }
  }
  if (!r.ok) {
    remove(robot);
    return r;
  }
  robots_[robot] = std::move(next);
  return r;
}

void GlobalFusion::remove(const std::string& robot) {
  const auto it = robots_.find(robot);
  if (it == robots_.end()) return;
  GlobalFuseResult ignored;
  add_full(it->second, -1, ignored);
  robots_.erase(it);
}

}  // namespace mapmerge
