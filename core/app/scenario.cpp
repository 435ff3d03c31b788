#include "scenario.hpp"

#include <algorithm>
#include <cmath>
#include <stdexcept>

#include "mapmerge/map/bounds.hpp"
#include "mapmerge/map/crop.hpp"

namespace mapmerge::app {

Scenario make_scenario(const octomap::OcTree& world, int n, double min_overlap, double max_overlap,
                       double max_tilt_deg, double max_offset, std::mt19937& rng) {
  if (n < 2) throw std::invalid_argument("a scenario needs at least two robots");
  const Eigen::AlignedBox3d bounds = leaf_bounds(world);
  const double x0 = bounds.min().x(), y0 = bounds.min().y(), z0 = bounds.min().z();
  const double x1 = bounds.max().x(), y1 = bounds.max().y(), z1 = bounds.max().z();
  const bool along_x = (x1 - x0) >= (y1 - y0);
  const double lo = along_x ? x0 : y0;
  const double extent = along_x ? x1 - x0 : y1 - y0;
  std::uniform_real_distribution<double> overlap(min_overlap, max_overlap);
  std::vector<double> overlaps(static_cast<std::size_t>(n), 0.0);
  double sum = 0.0;
  for (int i = 1; i < n; ++i) sum += (overlaps[static_cast<std::size_t>(i)] = overlap(rng));
  // n strips of length L, neighbours sharing overlap_i * L: extent = L * (n - sum of overlaps).
  const double length = extent / (n - sum);
  const double deg = M_PI / 180.0;
  std::uniform_real_distribution<double> yaw(-M_PI, M_PI), tilt(-max_tilt_deg * deg, max_tilt_deg * deg),
      offset(-max_offset, max_offset), lift(-0.5, 0.5);
  Scenario s;
  double start = lo;
  for (int i = 0; i < n; ++i) {
    ScenarioRobot r;
    r.id = "r" + std::to_string(i + 1);
    r.overlap_with_previous = overlaps[static_cast<std::size_t>(i)];
    if (i > 0) start -= r.overlap_with_previous * length;
    const double end = start + length;
    r.box = along_x ? Eigen::AlignedBox3d(Eigen::Vector3d(start, y0, z0), Eigen::Vector3d(end, y1, z1))
                    : Eigen::AlignedBox3d(Eigen::Vector3d(x0, start, z0), Eigen::Vector3d(x1, end, z1));
    const double x = offset(rng), y = offset(rng), z = lift(rng);
    const double roll = tilt(rng), pitch = tilt(rng), heading = yaw(rng);
    // The reference robot's frame (the global frame) is level and keeps the world's heading, so
    // the global map stands upright and reads like the source map; the others are turned
    // anywhere on the circle and tilted. Only frames relative to the reference matter.
    const double turned = i == 0 ? 0.0 : 1.0;
    r.T_robot_world = make_transform(x, y, z, turned * roll, turned * pitch, turned * heading);
    s.robots.push_back(r);
    start = end;
  }
  return s;
}

std::array<double, 16> to_row_major(const Eigen::Matrix4d& m) {
  std::array<double, 16> a{};
  for (int r = 0; r < 4; ++r)
    for (int c = 0; c < 4; ++c) a[static_cast<std::size_t>(4 * r + c)] = m(r, c);
  return a;
}

Eigen::Matrix4d from_row_major(const std::vector<double>& v) {
  if (v.size() != 16) throw std::invalid_argument("a transform needs 16 numbers (row-major 4x4)");
  Eigen::Matrix4d m;
  for (int r = 0; r < 4; ++r)
    for (int c = 0; c < 4; ++c) m(r, c) = v[static_cast<std::size_t>(4 * r + c)];
  return m;
}

}  // namespace mapmerge::app

namespace mapmerge::app {

PoseError pose_error(const Eigen::Matrix4d& T_true, const Eigen::Matrix4d& T_est) {
  const Eigen::Matrix3d dR = T_true.block<3, 3>(0, 0).transpose() * T_est.block<3, 3>(0, 0);
  const double c = std::clamp((dR.trace() - 1.0) / 2.0, -1.0, 1.0);
  PoseError e;
  e.rotation_deg = std::acos(c) * 180.0 / M_PI;
  e.translation_m = (T_est.block<3, 1>(0, 3) - T_true.block<3, 1>(0, 3)).norm();
  return e;
}

}  // namespace mapmerge::app
