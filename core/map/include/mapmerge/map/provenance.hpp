#pragma once
/// Which robot contributed each occupied voxel of a fused map, and where each robot's frame is.

#include <cstdint>
#include <string>
#include <unordered_map>
#include <vector>

#include <Eigen/Core>
#include <octomap/OcTreeKey.h>

namespace mapmerge {

/// A robot's name and pose in the global frame (drawn as axes by `mapmerge render`).
struct RobotFrame {
  std::string name;
  Eigen::Matrix4d T_global_robot = Eigen::Matrix4d::Identity();
};

/// The robot with the strongest occupied evidence for one voxel.
struct VoxelOwner {
  std::uint16_t robot = 0;  ///< index into Provenance::robots (or into the fused maps)
  float evidence = 0.0F;    ///< the log-odds that robot added [log-odds]; not stored on disk
};

/// Per-voxel provenance of a fused map, keyed at the map's full resolution.
struct Provenance {
  double resolution = 0.0;          ///< voxel edge of the keys [m]
  std::vector<RobotFrame> robots;   ///< index = VoxelOwner::robot
  std::unordered_map<octomap::OcTreeKey, VoxelOwner, octomap::OcTreeKey::KeyHash> owner;

  /// Records `robot` for `key` if it brings more evidence than the owner known so far.
  void vote(const octomap::OcTreeKey& key, std::uint16_t robot, float evidence) {
    auto [it, inserted] = owner.try_emplace(key, VoxelOwner{robot, evidence});
    if (!inserted && evidence > it->second.evidence) it->second = VoxelOwner{robot, evidence};
  }
};

/// Writes a provenance file (little-endian binary: "MMPROV1\n", resolution, robots with frames,
/// then one (key x, y, z, robot) record of 4 uint16 per voxel). Throws MapError on I/O failure.
void write_provenance(const Provenance& provenance, const std::string& path);

/// Reads a provenance file, checking every count against the file size. Throws MapError.
Provenance read_provenance(const std::string& path);

}  // namespace mapmerge
