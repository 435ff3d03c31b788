// Writes the fuzz seed corpus from the real maps in data/: small cuts of each map in every
// encoding (`.bt`, `.bt` + zstd, `.ot`, ROS 2 binary and full bodies) and the empty map. Only
// small cuts (a few KB): whole maps would cost the fuzzer seconds per run. Usage:
// fuzz_make_seeds DATA_DIR OUT_DIR
#include <cmath>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <string>
#include <vector>

#include <Eigen/Geometry>

#include "mapmerge/map/crop.hpp"
#include "mapmerge/map/map_codec.hpp"
#include "mapmerge/map/map_io.hpp"

namespace fs = std::filesystem;
using mapmerge::Encoding;

namespace {

void write(const fs::path& path, const std::vector<std::uint8_t>& bytes) {
  std::ofstream(path, std::ios::binary).write(reinterpret_cast<const char*>(bytes.data()),
                                              static_cast<std::streamsize>(bytes.size()));
}

void write_all_forms(const octomap::OcTree& tree, const fs::path& out, const std::string& stem) {
  write(out / (stem + ".bt"), mapmerge::encode_map(tree, Encoding::kOctomapBt));
  write(out / (stem + ".bt.zst"), mapmerge::encode_map(tree, Encoding::kOctomapBtZstd));
  write(out / (stem + ".ot"), mapmerge::encode_map(tree, Encoding::kOctomapOt));
  // ROS 2 bodies: first byte 0x00 = binary at 5 cm, 0x01 = full at 5 cm (see the fuzz target).
  for (const std::uint8_t mode : {0, 1}) {
    auto body = mapmerge::encode_tree_body(tree, mode == 0);
    body.insert(body.begin(), mode);
    write(out / (stem + (mode == 0 ? ".ros-binary" : ".ros-full")), body);
  }
}

}  // namespace

int main(int argc, char** argv) {
  if (argc != 3) {
    std::cerr << "usage: fuzz_make_seeds DATA_DIR OUT_DIR\n";
    return 2;
  }
  const fs::path data = argv[1], out = argv[2];
  fs::create_directories(out);
  write_all_forms(octomap::OcTree(0.05), out, "empty");
  for (const char* name : {"fr_079", "geb079", "fr_078_tidyup"}) {
    const auto tree = mapmerge::read_octree_file((data / (std::string(name) + ".bt")).string());
    // Small cuts around an occupied voxel near the map's middle: fast inputs for the fuzzer.
    double x0 = 0, y0 = 0, z0 = 0, x1 = 0, y1 = 0, z1 = 0;
    tree->getMetricMin(x0, y0, z0);
    tree->getMetricMax(x1, y1, z1);
    Eigen::Vector3d centre(0.5 * (x0 + x1), 0.5 * (y0 + y1), 0.5 * (z0 + z1));
    for (auto it = tree->begin_leafs(), end = tree->end_leafs(); it != end; ++it) {
      if (tree->isNodeOccupied(*it) && std::abs(it.getX() - centre.x()) < 3 && std::abs(it.getY() - centre.y()) < 3) {
        centre = Eigen::Vector3d(it.getX(), it.getY(), it.getZ());
        break;
      }
    }
    for (const double edge : {0.3, 0.6, 1.2}) {
      const Eigen::Vector3d lo = centre - Eigen::Vector3d::Constant(0.5 * edge);
      const auto part = mapmerge::crop_and_transform(
          *tree, Eigen::AlignedBox3d(lo, lo + Eigen::Vector3d::Constant(edge)), Eigen::Isometry3d::Identity());
      part->prune();
      write_all_forms(*part, out, std::string(name) + "-" + std::to_string(static_cast<int>(edge * 10)));
    }
  }
  std::cout << "seeds written to " << out << "\n";
  return 0;
}
