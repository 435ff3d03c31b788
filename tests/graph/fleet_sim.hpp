#pragma once
// A simulated fleet on a real map (tests and bench of core/graph).
//
// The occupied voxels of data/fr_079.bt (Freiburg building 079, 43.7 m x 18.2 m) are the world.
// Robot i starts at a point along the corridor (evenly spaced, jittered, seeded); its map frame
// is that start pose (yaw anywhere on the circle, roll/pitch of a few degrees) and its map is
// the part of the building within region_length/2 along x of its start (the whole width).
// Two robots share an edge when their maps share at least min_shared_points occupied voxels:
// what the server's overlap estimate would select. Each edge carries
//   - quality numbers as the alignment pipeline reports them: inliers = shared voxels after
//     the pipeline's voxel grid (2.5 x res: ~1/6 of surface voxels), capped by its ICP sample
//     (6000 points, both directions); overlap = shared / smaller map; fitness; pivot = centroid
//     of the shared voxels;
//   - T_target_source = truth perturbed at the pivot by rotation_noise_deg (RMS angle) and
//     translation_noise (RMS) scaled up for small overlaps, as the pipeline's errors are.
// A wrong edge is the truth turned about z at the pivot by 90..180 deg: the corridor
// feature match that lines up the walls the wrong way round.

#include <algorithm>
#include <cmath>
#include <memory>
#include <random>
#include <stdexcept>
#include <string>
#include <vector>

#include <Eigen/Geometry>
#include <octomap/OcTree.h>

#include "mapmerge/graph/information.hpp"
#include "mapmerge/graph/pose_graph.hpp"

namespace mapmerge::graph::sim {

struct World {
  std::vector<Eigen::Vector3d> occupied;  // leaf centres [m]
  Eigen::AlignedBox3d bounds;
};

/// The occupied voxels of a real map, loaded once per process.
inline const World& world(const std::string& path) {
  static std::unique_ptr<World> cached;
  if (cached) return *cached;
  octomap::OcTree tree(0.05);
  if (!tree.readBinary(path)) throw std::runtime_error("cannot read " + path);
  auto w = std::make_unique<World>();
  for (auto it = tree.begin_leafs(); it != tree.end_leafs(); ++it) {
    if (!tree.isNodeOccupied(*it)) continue;
    const Eigen::Vector3d p(it.getX(), it.getY(), it.getZ());
    w->occupied.push_back(p);
    w->bounds.extend(p);
  }
  cached = std::move(w);
  return *cached;
}

struct FleetConfig {
  int robots = 5;                    ///< [count]
  double region_length = 17.0;       ///< extent of each robot's map along the corridor [m]
  double position_jitter = 1.0;      ///< start positions vary by up to this along x and y [m]
  double tilt_deg = 2.0;             ///< roll/pitch sigma of a map frame [deg]
  std::size_t min_shared_points = 8000;  ///< shared occupied voxels for an edge (~1 m of corridor) [count]
  double fitness = 0.02;             ///< reported mean inlier distance [m]
  double voxels_per_inlier = 6.0;    ///< shared voxels per reported inlier (voxel grid) [ratio]
  std::size_t max_inliers = 12000;   ///< the pipeline's ICP sample, both directions [count]
  double rotation_noise_deg = 0.5;   ///< RMS rotation error of an edge at full overlap [deg]
  double translation_noise = 0.03;   ///< RMS translation error at the pivot at full overlap [m]
  double full_overlap = 0.3;         ///< overlap from which the noise does not grow [0..1]
  unsigned seed = 1;
};

struct SimEdge {
  Edge edge;
  AlignmentQuality quality;
  Eigen::Isometry3d T_true = Eigen::Isometry3d::Identity();  // true T_target_source
  int source = -1;
  int target = -1;
};

struct Fleet {
  std::vector<std::string> ids;
  std::vector<Eigen::Isometry3d> T_world_robot;  // truth
  std::vector<SimEdge> edges;
  std::vector<int> degree;

  /// True T_ref_robot.
  Eigen::Isometry3d truth(int reference, int robot) const {
    return T_world_robot[reference].inverse() * T_world_robot[robot];
  }
};

inline std::string robot_name(int i) { return "robot" + std::string(i < 10 ? "0" : "") + std::to_string(i); }

inline Eigen::Isometry3d perturb_at(const Eigen::Isometry3d& T, const Eigen::Vector3d& pivot,
                                    const Eigen::Vector3d& rotation_vector,
                                    const Eigen::Vector3d& translation) {
  Eigen::Isometry3d N = Eigen::Isometry3d::Identity();
  const double angle = rotation_vector.norm();
  if (angle > 0.0) N.linear() = Eigen::AngleAxisd(angle, rotation_vector / angle).toRotationMatrix();
  N.translation() = translation;
  const Eigen::Translation3d to(pivot), back(-pivot);
  return T * (to * N * back);
}

inline Fleet make_fleet(const World& w, const FleetConfig& c, const InformationConfig& info = {}) {
  std::mt19937 rng(c.seed);
  std::uniform_real_distribution<double> uni(-1.0, 1.0);
  std::normal_distribution<double> gauss(0.0, 1.0);
  constexpr double kPi = 3.14159265358979323846;
  const double deg = kPi / 180.0;
  Fleet f;
  const double half = 0.5 * c.region_length;
  const double x0 = w.bounds.min().x() + half;
  const double x1 = w.bounds.max().x() - half;
  const Eigen::Vector3d centre = w.bounds.center();
  std::vector<Eigen::AlignedBox3d> region;
  for (int i = 0; i < c.robots; ++i) {
    const double s = c.robots > 1 ? static_cast<double>(i) / (c.robots - 1) : 0.5;
    const Eigen::Vector3d p(x0 + s * (x1 - x0) + c.position_jitter * uni(rng),
                            centre.y() + c.position_jitter * uni(rng), 0.1 * gauss(rng));
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    T.linear() = (Eigen::AngleAxisd(kPi * uni(rng), Eigen::Vector3d::UnitZ()) *
                  Eigen::AngleAxisd(c.tilt_deg * deg * gauss(rng), Eigen::Vector3d::UnitY()) *
                  Eigen::AngleAxisd(c.tilt_deg * deg * gauss(rng), Eigen::Vector3d::UnitX()))
                     .toRotationMatrix();
    T.translation() = p;
    f.ids.push_back(robot_name(i));
    f.T_world_robot.push_back(T);
    Eigen::AlignedBox3d box = w.bounds;
    box.min().x() = p.x() - half;
    box.max().x() = p.x() + half;
    region.push_back(box);
  }
  std::vector<std::size_t> points(c.robots, 0);
  for (const auto& q : w.occupied)
    for (int i = 0; i < c.robots; ++i) points[i] += region[i].contains(q) ? 1 : 0;
  f.degree.assign(c.robots, 0);
  for (int t = 0; t < c.robots; ++t) {
    for (int s = t + 1; s < c.robots; ++s) {
      const Eigen::AlignedBox3d shared = region[t].intersection(region[s]);
      if (shared.isEmpty()) continue;
      std::size_t n = 0;
      Eigen::Vector3d sum = Eigen::Vector3d::Zero();
      for (const auto& q : w.occupied)
        if (shared.contains(q)) {
          ++n;
          sum += q;
        }
      if (n < c.min_shared_points) continue;
      SimEdge e;
      e.source = s;
      e.target = t;
      e.T_true = f.T_world_robot[t].inverse() * f.T_world_robot[s];
      e.quality.inliers = std::min(c.max_inliers, static_cast<std::size_t>(static_cast<double>(n) / c.voxels_per_inlier));
      e.quality.fitness = c.fitness;
      e.quality.overlap = static_cast<double>(n) / static_cast<double>(std::min(points[t], points[s]));
      e.quality.pivot_source = f.T_world_robot[s].inverse() * (sum / static_cast<double>(n));
      const double grow = std::sqrt(c.full_overlap / std::clamp(e.quality.overlap, 0.05, c.full_overlap));
      const double sr = grow * c.rotation_noise_deg * deg / std::sqrt(3.0);
      const double st = grow * c.translation_noise / std::sqrt(3.0);
      const Eigen::Vector3d rv(sr * gauss(rng), sr * gauss(rng), sr * gauss(rng));
      const Eigen::Vector3d tv(st * gauss(rng), st * gauss(rng), st * gauss(rng));
      e.edge.source = f.ids[s];
      e.edge.target = f.ids[t];
      e.edge.T_target_source = perturb_at(e.T_true, e.quality.pivot_source, rv, tv);
      const EdgeInformation ei = information_from_alignment(e.quality, info);
      if (!ei.valid) throw std::runtime_error("sim: " + ei.reason);
      e.edge.information = ei.information;
      f.edges.push_back(e);
      ++f.degree[t];
      ++f.degree[s];
    }
  }
  return f;
}

/// Turns edge k into a wrong match: the truth turned about z by angle_deg at the pivot.
inline void make_wrong(Fleet& f, std::size_t k, double angle_deg) {
  SimEdge& e = f.edges.at(k);
  const Eigen::Vector3d z_in_source =
      f.T_world_robot[e.source].linear().transpose() * Eigen::Vector3d::UnitZ();
  e.edge.T_target_source = perturb_at(e.T_true, e.quality.pivot_source,
                                      z_in_source * angle_deg * 3.14159265358979323846 / 180.0,
                                      Eigen::Vector3d::Zero());
}

inline void load(PoseGraph& g, const Fleet& f, int reference) {
  g.set_reference(f.ids[reference]);
  for (const auto& id : f.ids) g.add_robot(id);
  for (const auto& e : f.edges) g.add_or_update_edge(e.edge);
}

struct PoseError {
  double rotation_deg = 0.0;
  double translation = 0.0;  // [m]
};

inline PoseError pose_error(const Eigen::Isometry3d& estimate, const Eigen::Isometry3d& truth) {
  const Eigen::Isometry3d d = truth.inverse() * estimate;
  const Eigen::Quaterniond q(d.linear());
  return {2.0 * std::atan2(q.vec().norm(), std::abs(q.w())) * 180.0 / 3.14159265358979323846,
          (estimate.translation() - truth.translation()).norm()};
}

}  // namespace mapmerge::graph::sim
