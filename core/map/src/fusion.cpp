#include "mapmerge/map/fusion.hpp"

#include <algorithm>
#include <cmath>

#include <Eigen/Geometry>

#include "mapmerge/map/map_io.hpp"
#include "tree_scan.hpp"
#include "tree_writer.hpp"

namespace mapmerge {
namespace {

constexpr int kKeyCentre = 32768;  ///< OctoMap's key of the voxel just above coordinate 0
constexpr int kKeyMax = 65535;

/// Places source leaves (oriented cubes once moved) onto the target's voxel grid.
class LeafMapper {
 public:
  LeafMapper(const Eigen::Matrix4d& T_target_source, double target_res, detail::TreeWriter& writer,
             Provenance* provenance, std::uint16_t robot, FuseResult& stats)
      : R_(T_target_source.topLeftCorner<3, 3>()),
        Rt_(R_.transpose()),
        t_(T_target_source.topRightCorner<3, 1>()),
        res_(target_res),
        abs_Rt_row_sum_(Rt_.cwiseAbs().rowwise().sum()),
        abs_R_row_sum_(R_.cwiseAbs().rowwise().sum()),
        writer_(writer),
        provenance_(provenance),
        robot_(robot),
        stats_(stats) {}

  /// Adds `delta` to every target voxel whose centre lies in the cube (centre `c`, edge `size`,
  /// source frame). Half-open bounds give each target voxel to exactly one source leaf.
  void add_cube(const Eigen::Vector3d& c, double size, float delta) {
    c_ = c;
    h_ = 0.5 * size;
    delta_ = delta;
    const Eigen::Vector3d ct = R_ * c + t_;
    const Eigen::Vector3d e = h_ * abs_R_row_sum_;
    int lo[3];
    int hi[3];
    bool clipped = false;
    for (int i = 0; i < 3; ++i) {
      lo[i] = static_cast<int>(std::ceil((ct[i] - e[i]) / res_ + (kKeyCentre - 0.5) - 1e-9));
      hi[i] = static_cast<int>(std::floor((ct[i] + e[i]) / res_ + (kKeyCentre - 0.5) + 1e-9));
      clipped |= lo[i] < 0 || hi[i] > kKeyMax;
      lo[i] = std::max(lo[i], 0);
      hi[i] = std::min(hi[i], kKeyMax);
      if (lo[i] > hi[i]) {
        ++stats_.leaves_clipped;
        return;
      }
    }
    stats_.leaves_clipped += clipped;
    // Largest aligned target block that may fit inside the cube.
    unsigned level = 0;
    while (level < 15 && static_cast<double>(2U << level) * res_ <= size * (1 + 1e-9)) ++level;
    for (int x = lo[0] >> level; x <= hi[0] >> level; ++x) {
      for (int y = lo[1] >> level; y <= hi[1] >> level; ++y) {
        for (int z = lo[2] >> level; z <= hi[2] >> level; ++z) {
          visit(x << level, y << level, z << level, level);
        }
      }
    }
  }

 private:
  /// The aligned block of 2^level voxels per side at key (x, y, z): update it whole when all its
  /// voxel centres are inside the cube, skip it when none can be, otherwise split it.
  void visit(int x, int y, int z, unsigned level) {
    if (x > kKeyMax || y > kKeyMax || z > kKeyMax) return;
    const double a = 0.5 * ((1 << level) - 1) * res_;  // centre-to-outer-voxel-centre offset
    const Eigen::Vector3d mid((x - kKeyCentre + 0.5) * res_ + a, (y - kKeyCentre + 0.5) * res_ + a,
                              (z - kKeyCentre + 0.5) * res_ + a);
    const Eigen::Vector3d p = Rt_ * (mid - t_) - c_;  // block middle in the leaf's frame
    const Eigen::Vector3d reach = a * abs_Rt_row_sum_;
    bool inside = true;
    for (int i = 0; i < 3; ++i) {
      if (p[i] + reach[i] < -h_ || p[i] - reach[i] >= h_) return;  // no centre can be inside
      inside &= p[i] - reach[i] >= -h_ && p[i] + reach[i] < h_;
    }
    if (inside) {
      apply(x, y, z, level);
      return;
    }
    if (level == 0) return;
    const int half = 1 << (level - 1);
    for (int i = 0; i < 8; ++i) {
      visit(x + (i & 1) * half, y + ((i >> 1) & 1) * half, z + ((i >> 2) & 1) * half, level - 1);
    }
  }

  void apply(int x, int y, int z, unsigned level) {
    const octomap::OcTreeKey key(static_cast<octomap::key_type>(x),
                                 static_cast<octomap::key_type>(y),
                                 static_cast<octomap::key_type>(z));
    writer_.add(key, level, delta_);
    if (level == 0) {
      ++stats_.voxel_updates;
    } else {
      ++stats_.block_updates;
    }
    if (provenance_ == nullptr || delta_ <= 0) return;
    const int n = 1 << level;
    for (int i = 0; i < n * n * n; ++i) {
      const octomap::OcTreeKey voxel(static_cast<octomap::key_type>(x + i % n),
                                     static_cast<octomap::key_type>(y + (i / n) % n),
                                     static_cast<octomap::key_type>(z + i / (n * n)));
      provenance_->vote(voxel, robot_, delta_);
    }
  }

  Eigen::Matrix3d R_;
  Eigen::Matrix3d Rt_;
  Eigen::Vector3d t_;
  double res_;
  Eigen::Vector3d abs_Rt_row_sum_;
  Eigen::Vector3d abs_R_row_sum_;
  detail::TreeWriter& writer_;
  Provenance* provenance_;
  std::uint16_t robot_;
  FuseResult& stats_;
  Eigen::Vector3d c_;
  double h_ = 0.0;
  float delta_ = 0.0F;
};

std::string check_rigid(const Eigen::Matrix4d& T, double tolerance) {
  if (!T.allFinite()) return "transform has non-finite entries";
  if (!T.row(3).isApprox(Eigen::RowVector4d(0, 0, 0, 1), tolerance)) {
    return "transform's last row is not (0, 0, 0, 1)";
  }
  const Eigen::Matrix3d R = T.topLeftCorner<3, 3>();
  if ((R.transpose() * R - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff() > tolerance ||
      R.determinant() < 0) {
    return "transform's rotation is not a proper rotation";
  }
  return "";
}

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

/// Upper bound of the target voxel visits fusing `source` costs (see FuseConfig::max_work).
double estimate_work(const octomap::OcTree& source, double target_res, bool fuse_free) {
  double work = 0.0;
  for (auto it = source.begin_leafs(), end = source.end_leafs(); it != end; ++it) {
    if (!fuse_free && !source.isNodeOccupied(*it)) continue;
    work += detail::leaf_fusion_work(std::max(1.0, std::ceil(it.getSize() / target_res)));
  }
  return work;
}

}  // namespace

FuseResult fuse_into(octomap::OcTree& target, const octomap::OcTree& source,
                     const Eigen::Matrix4d& T_target_source, const FuseConfig& config) {
  return fuse_into(target, source, T_target_source, config, nullptr, 0);
}

FuseResult fuse_into(octomap::OcTree& target, const octomap::OcTree& source,
                     const Eigen::Matrix4d& T_target_source, const FuseConfig& config,
                     Provenance* provenance, std::uint16_t robot) {
  FuseResult result;
  result.reason = check_rigid(T_target_source, config.rigid_tolerance);
  if (!result.reason.empty()) return result;
  const double res = target.getResolution();
  const double work = estimate_work(source, res, config.fuse_free);
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
  LeafMapper mapper(T_target_source, res, writer, provenance, robot, result);
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
