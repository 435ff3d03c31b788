#include "mapmerge/map/fusion.hpp"

#include <algorithm>
#include <cmath>

#include <Eigen/Geometry>

#include "mapmerge/map/map_io.hpp"
#include "leaf_mapper.hpp"
#include "tree_scan.hpp"
#include "tree_writer.hpp"

namespace mapmerge {
namespace {

using KeyVotes = std::unordered_map<octomap::OcTreeKey, float, octomap::OcTreeKey::KeyHash>;

/// Source leaves finer than the target's voxels vote for the voxel holding their centre; the
/// largest vote per voxel (occupied over free) is added once.
void add_votes(const KeyVotes& votes, detail::TreeWriter& writer, Provenance* provenance,
               std::uint16_t robot, FuseResult& stats) {
  for (const auto& [key, delta] : votes) {
    writer.add(key, 0, delta);
    ++stats.voxel_updates;
    if (provenance != nullptr && delta > 0) provenance->vote(key, robot, delta);
  }
}

/// fuse_into()'s sink: log-odds added to the target (clamped), occupied evidence voted for.
struct WriterSink {
  detail::TreeWriter& writer;
  Provenance* provenance;
  std::uint16_t robot;

  void apply(const octomap::OcTreeKey& key, unsigned level, float delta) {
    writer.add(key, level, delta);
    if (provenance == nullptr || delta <= 0) return;
    const int n = 1 << level;
    for (int i = 0; i < n * n * n; ++i) {
      const octomap::OcTreeKey voxel(static_cast<octomap::key_type>(key[0] + i % n),
                                     static_cast<octomap::key_type>(key[1] + (i / n) % n),
                                     static_cast<octomap::key_type>(key[2] + i / (n * n)));
      provenance->vote(voxel, robot, delta);
    }
  }
};

}  // namespace

FuseResult fuse_into(octomap::OcTree& target, const octomap::OcTree& source,
                     const Eigen::Matrix4d& T_target_source, const FuseConfig& config) {
  return fuse_into(target, source, T_target_source, config, nullptr, 0);
}

FuseResult fuse_into(octomap::OcTree& target, const octomap::OcTree& source,
                     const Eigen::Matrix4d& T_target_source, const FuseConfig& config,
                     Provenance* provenance, std::uint16_t robot) {
  FuseResult result;
  result.reason = detail::check_rigid(T_target_source, config.rigid_tolerance);
  if (!result.reason.empty()) return result;
  const double res = target.getResolution();
  const double work = detail::estimate_work(source, res, config.fuse_free);
  if (work > config.max_work) {
    result.reason = "source would cost ~" + std::to_string(static_cast<long long>(work)) +
                    " voxel visits, more than max_work (huge pruned leaves?)";
    return result;
  }
  if (provenance != nullptr) {
    provenance->resolution = res;
    provenance->owner.reserve(provenance->owner.size() + source.getNumLeafNodes() / 2);
  }
  detail::TreeWriter writer(target);
  WriterSink sink{writer, provenance, robot};
  detail::LeafMapper<WriterSink, float> mapper(T_target_source, res, sink, result);
  KeyVotes fine_votes;
  for (auto it = source.begin_leafs(), end = source.end_leafs(); it != end; ++it) {
    const float delta = it->getLogOdds();
    ++result.source_leaves;
    if (delta == 0.0F || (delta < 0.0F && !config.fuse_free)) continue;
    const double size = it.getSize();
    const Eigen::Vector3d c(it.getX(), it.getY(), it.getZ());
    if (size >= res * (1 - 1e-9)) {
      mapper.add_cube(c, size, delta);
      continue;
    }
    octomap::OcTreeKey key;
    const Eigen::Vector3d ct = T_target_source.topLeftCorner<3, 3>() * c +
                               T_target_source.topRightCorner<3, 1>();
    if (!target.coordToKeyChecked(ct.x(), ct.y(), ct.z(), key)) {
      ++result.leaves_clipped;
      continue;
    }
    auto [vote, inserted] = fine_votes.try_emplace(key, delta);
    if (!inserted) vote->second = std::max(vote->second, delta);
  }
  add_votes(fine_votes, writer, provenance, robot, result);
  target.updateInnerOccupancy();
  if (config.prune) target.prune();
  result.ok = true;
  return result;
}

FusedMap fuse_maps_with_provenance(const std::vector<MapInGlobal>& maps_in_global,
                                   double resolution) {
  if (!(resolution > 0.0) || !std::isfinite(resolution)) {
    throw MapError("fuse_maps: resolution must be positive");
  }
  FusedMap fused;
  fused.tree = std::make_unique<octomap::OcTree>(resolution);
  fused.provenance.resolution = resolution;
  FuseConfig config;
  config.prune = false;
  for (std::size_t i = 0; i < maps_in_global.size(); ++i) {
    const auto& [map, T_global_map] = maps_in_global[i];
    if (map == nullptr) throw MapError("fuse_maps: map " + std::to_string(i) + " is null");
    const FuseResult r = fuse_into(*fused.tree, *map, T_global_map, config, &fused.provenance,
                                   static_cast<std::uint16_t>(i));
    if (!r.ok) throw MapError("fuse_maps: map " + std::to_string(i) + ": " + r.reason);
    fused.provenance.robots.push_back(RobotFrame{"map " + std::to_string(i), T_global_map});
  }
  fused.tree->prune();
  return fused;
}

std::unique_ptr<octomap::OcTree> fuse_maps(const std::vector<MapInGlobal>& maps_in_global,
                                           double resolution) {
  if (!(resolution > 0.0) || !std::isfinite(resolution)) {
    throw MapError("fuse_maps: resolution must be positive");
  }
  auto tree = std::make_unique<octomap::OcTree>(resolution);
  FuseConfig config;
  config.prune = false;
  for (std::size_t i = 0; i < maps_in_global.size(); ++i) {
    const auto& [map, T_global_map] = maps_in_global[i];
    if (map == nullptr) throw MapError("fuse_maps: map " + std::to_string(i) + " is null");
    const FuseResult r = fuse_into(*tree, *map, T_global_map, config);
    if (!r.ok) throw MapError("fuse_maps: map " + std::to_string(i) + ": " + r.reason);
  }
  tree->prune();
  return tree;
}

}  // namespace mapmerge
