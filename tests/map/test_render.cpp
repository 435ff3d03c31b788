// Rendering: picture size, occupied regions visible against the background, robot colouring.
#include <gtest/gtest.h>

#include <algorithm>
#include <fstream>

#include "map_test_util.hpp"
#include "mapmerge/map/fusion.hpp"
#include "mapmerge/map/map_codec.hpp"
#include "mapmerge/map/render.hpp"

namespace mapmerge {
namespace {

bool coloured(const std::uint8_t* p) {
  const int hi = std::max({p[0], p[1], p[2]});
  const int lo = std::min({p[0], p[1], p[2]});
  return hi - lo > 40;  // the backgrounds, text and free space are all grey
}

std::size_t count_coloured(const Image& image, int x0, int x1) {
  std::size_t n = 0;
  for (int y = 0; y < image.height; ++y) {
    for (int x = x0; x < x1; ++x) n += coloured(image.pixel(x, y));
  }
  return n;
}

/// A solid 1 m cube of occupied voxels around `centre`.
octomap::OcTree cube(const octomap::point3d& centre, double res) {
  octomap::OcTree tree(res);
  for (float x = -0.5F; x < 0.5F; x += static_cast<float>(res)) {
    for (float y = -0.5F; y < 0.5F; y += static_cast<float>(res)) {
      for (float z = -0.5F; z < 0.5F; z += static_cast<float>(res)) {
        tree.updateNode(centre + octomap::point3d(x, y, z), true);
      }
    }
  }
  return tree;
}

TEST(Render, PictureHasTheRequestedSize) {
  const auto tree = test::load("geb079.bt");
  RenderConfig config;
  config.width = 1200;
  config.height = 700;
  const Image image = render_map(*tree, config, nullptr);
  EXPECT_EQ(image.width, 1200);
  EXPECT_EQ(image.height, 700);
  EXPECT_EQ(image.rgb.size(), 1200U * 700U * 3U);
}

TEST(Render, OccupiedRegionsDifferFromTheBackground) {
  const octomap::OcTree block = cube(octomap::point3d(3, -2, 1), 0.1);
  RenderConfig config;
  config.width = 1200;
  config.height = 700;
  const Image image = render_map(block, config, nullptr);
  // The cube is centred in each panel: the middle rows of each half of the picture show it, the
  // corners of the panels do not.
  for (const int x : {image.width / 4, 3 * image.width / 4}) {
    int hits = 0;
    for (int y = image.height / 3; y < 2 * image.height / 3; ++y) hits += coloured(image.pixel(x, y));
    EXPECT_GT(hits, 20) << "panel at x=" << x;
  }
  EXPECT_FALSE(coloured(image.pixel(60, 120)));
  EXPECT_FALSE(coloured(image.pixel(image.width - 60, 120)));

  const octomap::OcTree empty(0.1);
  const Image blank = render_map(empty, config, nullptr);
  EXPECT_EQ(count_coloured(blank, 0, blank.width), 0U);  // no voxels, no height legend
}

TEST(Render, HugeOccupiedLeafIsDrawnWithoutExpandingIt) {
  // An occupied leaf at depth 8, 256 voxels wide (16.7 M voxels, inside the decode limits), as a
  // pruned map may hold: drawn as one cube, not as 16.7 M splats.
  std::vector<std::uint8_t> body;
  for (int depth = 0; depth < 7; ++depth) body.insert(body.end(), {0x03, 0x00});
  body.insert(body.end(), {0x02, 0x00});
  const DecodeResult big = decode_tree_body("OcTree", 0.1, true, body, DecodeLimits{});
  ASSERT_TRUE(big.ok()) << big.reason;
  RenderConfig config;
  config.width = 800;
  config.height = 600;
  const Image image = render_map(*big.tree, config, nullptr);
  EXPECT_GT(count_coloured(image, 0, image.width), 10000U);
}

TEST(Render, RealMapFillsBothViews) {
  const auto tree = test::load("fr_078_tidyup.bt");
  RenderConfig config;
  config.width = 1400;
  config.height = 800;
  const Image image = render_map(*tree, config, nullptr);
  const double half = 0.5 * image.width * image.height;
  EXPECT_GT(count_coloured(image, 0, image.width / 2) / half, 0.10);
  EXPECT_GT(count_coloured(image, image.width / 2, image.width) / half, 0.10);
}

TEST(Render, ByRobotColoursEachContributorAndWritesAPng) {
  const auto tree = test::load("geb079.bt");
  double x0 = 0, y0 = 0, z0 = 0, x1 = 0, y1 = 0, z1 = 0;
  tree->getMetricMin(x0, y0, z0);
  tree->getMetricMax(x1, y1, z1);
  // Two "robots": the halves of the map, fused with provenance.
  octomap::OcTree left(tree->getResolution()), right(tree->getResolution());
  for (auto it = tree->begin_leafs(), end = tree->end_leafs(); it != end; ++it) {
    (it.getX() < 0.5 * (x0 + x1) ? left : right).setNodeValue(it.getKey(), it->getLogOdds());
  }
  const Eigen::Matrix4d I = Eigen::Matrix4d::Identity();
  FusedMap fused = fuse_maps_with_provenance({{&left, I}, {&right, I}}, tree->getResolution());
  fused.provenance.robots[0].name = "alpha";
  fused.provenance.robots[1].name = "bravo";
  RenderConfig config;
  config.frames = fused.provenance.robots;
  const Image image = render_map(*fused.tree, config, &fused.provenance);
  std::size_t blue = 0, orange = 0;
  for (int y = 0; y < image.height; ++y) {
    for (int x = 0; x < image.width; ++x) {
      const std::uint8_t* p = image.pixel(x, y);
      blue += p[2] > p[0] + 60 && p[2] > p[1];              // robot 0: (31, 119, 180)
      orange += p[0] > p[2] + 100 && p[1] > p[2] + 40;      // robot 1: (255, 127, 14)
    }
  }
  EXPECT_GT(blue, 5000U);
  EXPECT_GT(orange, 5000U);

  const std::string path = ::testing::TempDir() + "/by_robot.png";
  write_png(image, path);
  std::ifstream in(path, std::ios::binary);
  char magic[8] = {};
  in.read(magic, 8);
  EXPECT_EQ(std::string(magic + 1, 3), "PNG");
  EXPECT_THROW(write_png(image, "/nonexistent-dir/x.png"), MapError);
}

}  // namespace
}  // namespace mapmerge
