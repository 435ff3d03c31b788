#pragma once
/// Partial robot maps cut from one real map, with the ground truth of each robot's frame.

#include <array>
#include <random>
#include <string>
#include <vector>

#include <Eigen/Geometry>
#include <octomap/OcTree.h>

namespace mapmerge::app {

struct ScenarioRobot {
  std::string id;                   ///< "r1", "r2", ...
  Eigen::AlignedBox3d box;          ///< the part of the world map it saw [m, world frame]
  Eigen::Isometry3d T_robot_world;  ///< where the world lies in the robot's map frame
  double overlap_with_previous = 0; ///< share of this robot's strip also in the previous one [0..1]
};

struct Scenario {
  std::vector<ScenarioRobot> robots;  ///< robots[0] is the reference: its frame is `global`
  /// The true transform of a robot's map frame into the global (reference robot's) frame.
  Eigen::Isometry3d true_T_global_robot(const ScenarioRobot& robot) const {
    return robots.front().T_robot_world * robot.T_robot_world.inverse();
  }
};

/// Cuts the world's extent along its longest horizontal axis into `n` overlapping strips, each
/// overlapping its predecessor by a share drawn in [min_overlap, max_overlap], and gives each
/// robot a random frame (yaw anywhere on the circle, roll/pitch within max_tilt_deg); the first
/// robot's frame, the reference, is only shifted (level, with the world's heading).
Scenario make_scenario(const octomap::OcTree& world, int n, double min_overlap, double max_overlap,
                       double max_tilt_deg, double max_offset, std::mt19937& rng);

std::array<double, 16> to_row_major(const Eigen::Matrix4d& m);
Eigen::Matrix4d from_row_major(const std::vector<double>& v);

}  // namespace mapmerge::app

namespace mapmerge::app {

struct PoseError {
  double rotation_deg = 0.0;   ///< angle of R_true^T R_est [deg]
  double translation_m = 0.0;  ///< |t_est - t_true| [m]
};
PoseError pose_error(const Eigen::Matrix4d& T_true, const Eigen::Matrix4d& T_est);

}  // namespace mapmerge::app
