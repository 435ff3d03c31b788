#pragma once
/// Five robots cut from one real map (data/geb079.bt, the 39 m corridor at 8 cm), each in its
/// own frame with the truth known: 16 m strips 5.5 m apart, so each robot overlaps its
/// neighbours by 10.5 m and the robots two along by 5 m. Seven pairs overlap; a spanning tree
/// needs four, the other three close loops. Shared by the server's fleet test, the registry test
/// and the pose-graph test on real alignments (link mapmerge::align).

#include <memory>
#include <string>
#include <utility>
#include <vector>

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <octomap/OcTree.h>

#include "mapmerge/map/crop.hpp"
#include "mapmerge/map/map_io.hpp"

namespace mapmerge::test {

struct FiveRobots {
  std::shared_ptr<const octomap::OcTree> world;
  std::vector<std::string> ids{"r1", "r2", "r3", "r4", "r5"};
  std::vector<Eigen::AlignedBox3d> boxes;             ///< what each robot saw [m, world frame]
  std::vector<Eigen::Matrix4d> T_robot_world;         ///< where the world lies in each robot's frame
  std::vector<std::shared_ptr<const octomap::OcTree>> maps;  ///< in the robots' frames
  /// The pairs (i < j) whose strips overlap: (0,1) (0,2) (1,2) (1,3) (2,3) (2,4) (3,4).
  std::vector<std::pair<int, int>> overlapping;

  /// True T_a_b: robot b's map frame into robot a's.
  Eigen::Matrix4d truth(std::size_t a, std::size_t b) const {
    return T_robot_world[a] * T_robot_world[b].inverse();
  }
  /// The world's vertical axis in robot i's frame.
  Eigen::Vector3d up(std::size_t i) const { return T_robot_world[i].topLeftCorner<3, 3>() * Eigen::Vector3d::UnitZ(); }

  static const FiveRobots& get() {
    static const FiveRobots f = make();
    return f;
  }

 private:
  static FiveRobots make() {
    FiveRobots f;
    f.world = read_octree_file(std::string(MAPMERGE_DATA_DIR) + "/geb079.bt");
    const double x0[] = {-8.0, -2.5, 3.0, 8.5, 14.0};
    const double x1[] = {8.0, 13.5, 19.0, 24.5, 31.0};
    f.T_robot_world = {mapmerge::paper_transform(1, 2, 0, 0, 0, 30), mapmerge::paper_transform(-4, 7, 0.3, -3, 2, 155),
                       mapmerge::paper_transform(5, -3, 0.2, 2, -1, -70), mapmerge::paper_transform(-2, -6, -0.1, 1, 3, 100),
                       mapmerge::paper_transform(3, 4, 0.1, -2, -1, -140)};
    for (std::size_t i = 0; i < 5; ++i) {
      f.boxes.emplace_back(Eigen::Vector3d(x0[i], -8, -1), Eigen::Vector3d(x1[i], 8, 4));
      f.maps.push_back(crop_and_transform(*f.world, f.boxes[i], Eigen::Isometry3d(f.T_robot_world[i])));
    }
    for (int i = 0; i < 5; ++i)
      for (int j = i + 1; j < 5; ++j)
        if (x1[i] > x0[j]) f.overlapping.emplace_back(i, j);
    return f;
  }
};

}  // namespace mapmerge::test
