#include <algorithm>
#include <cmath>
#include <limits>

#include <gtest/gtest.h>

#include <Eigen/Geometry>

#include "mapmerge/align/stages.hpp"
#include "mapmerge/map/bounds.hpp"
#include "mapmerge/map/crop.hpp"
#include "mapmerge/map/held_map.hpp"
#include "mapmerge/map/leaf_set.hpp"
#include "mapmerge/map/map_codec.hpp"
#include "mapmerge/map/map_io.hpp"

namespace ma = mapmerge::align;

TEST(ToPoints, ExpandsPrunedLeavesAndKeepsOccupancy) {
  octomap::OcTree tree(0.1);
  // A 2x2x2 block of occupied voxels aligned to a depth-15 node: pruned into one leaf.
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 2; ++j)
      for (int k = 0; k < 2; ++k) tree.updateNode(0.05 + 0.1 * i, 0.05 + 0.1 * j, 0.05 + 0.1 * k, true);
  tree.updateNode(1.05, 1.05, 1.05, false);  // free: not a point
  tree.updateNode(2.05, 2.05, 2.05, true);
  tree.prune();
  ASSERT_LT(tree.getNumLeafNodes(), 10U);  // the block really is one pruned leaf
  const auto points = ma::to_points(tree, {});
  ASSERT_EQ(points.size(), 9U);
  for (const auto& p : points) {
    EXPECT_NEAR(p.occupancy, tree.search(p.position.x(), p.position.y(), p.position.z())->getOccupancy(), 1e-6);
    EXPECT_GT(p.occupancy, 0.5F);
    EXPECT_GT((p.position - Eigen::Vector3f(1.05F, 1.05F, 1.05F)).norm(), 0.01F);
  }
}

TEST(ToPoints, RealMapCountsEveryOccupiedVoxel) {
  const auto tree = mapmerge::read_octree_file(std::string(MAPMERGE_DATA_DIR) + "/geb079.bt");
  const auto points = ma::to_points(*tree, {});
  const Eigen::AlignedBox3d all(Eigen::Vector3d::Constant(-1e6), Eigen::Vector3d::Constant(1e6));
  EXPECT_EQ(points.size(), mapmerge::count_occupied(*tree, all));
  EXPECT_GT(points.size(), tree->getNumLeafNodes() / 10);
  ma::ToPointsConfig tight;
  tight.max_points = 1000;
  EXPECT_THROW(ma::to_points(*tree, tight), std::invalid_argument);
}

namespace {

/// `tree` as a robot's update arrives: its `.bt` bytes, checked and held undecoded.
std::shared_ptr<const mapmerge::HeldMap> held_bt(const octomap::OcTree& tree) {
  const auto bytes = mapmerge::encode_map(tree, mapmerge::Encoding::kOctomapBt);
  mapmerge::CheckedMap c = mapmerge::check_map(bytes.data(), bytes.size(), mapmerge::Encoding::kOctomapBt, {});
  EXPECT_TRUE(c.ok()) << c.reason;
  return c.map;
}

void expect_same_points(const std::vector<ma::OccupiedPoint>& a, const std::vector<ma::OccupiedPoint>& b) {
  ASSERT_EQ(a.size(), b.size());
  for (std::size_t i = 0; i < a.size(); ++i) {
    ASSERT_EQ(a[i].position, b[i].position) << "point " << i;
    ASSERT_EQ(a[i].occupancy, b[i].occupancy) << "point " << i;
  }
}

}  // namespace

TEST(ToPoints, ABinaryBodyGivesItsTreesPointsInTheTreesOrderWithoutBuildingIt) {
  octomap::OcTree pruned(0.1);  // a pruned leaf, a lone voxel, free space, negative coordinates
  for (int i = 0; i < 4; ++i)
    for (int j = 0; j < 4; ++j)
      for (int k = 0; k < 4; ++k) pruned.updateNode(-0.35 + 0.1 * i, 0.05 + 0.1 * j, -0.35 + 0.1 * k, true);
  pruned.updateNode(1.05, -1.05, 1.05, false);
  pruned.updateNode(2.05, -2.05, 0.05, true);
  pruned.prune();
  const auto geb = mapmerge::read_octree_file(std::string(MAPMERGE_DATA_DIR) + "/geb079.bt");
  for (const octomap::OcTree* tree : {&pruned, geb.get()}) {
    const auto held = held_bt(*tree);
    ASSERT_TRUE(held && held->binary_body());
    const auto from_body = ma::to_points(*held, {});
    EXPECT_FALSE(held->has_tree());
    expect_same_points(from_body, ma::to_points(*held->tree(), {}));
    // The positions are the original tree's; the occupancy is the body's (a clamped occupied leaf).
    const auto original = ma::to_points(*tree, {});
    ASSERT_EQ(from_body.size(), original.size());
    for (std::size_t i = 0; i < original.size(); ++i) ASSERT_EQ(from_body[i].position, original[i].position);
    ma::ToPointsConfig tight;
    tight.max_points = from_body.size() - 1;
    EXPECT_THROW(ma::to_points(*held, tight), std::invalid_argument);
  }
  EXPECT_EQ(held_bt(pruned)->occupied_leaves()->size(), 2U);  // the 4x4x4 block is one leaf
}

TEST(ToPoints, AFullBodyGivesItsTreesPointsLeavesAndBoundsWithoutBuildingIt) {
  // A `.ot` map is kept as its full body (log-odds per node): its points (with each leaf's own
  // occupancy), free and occupied leaf sets and bounds must be its tree's, read off the bytes.
  octomap::OcTree graded(0.1);  // a pruned block, leaves of graded log-odds, free space
  for (int i = 0; i < 4; ++i)
    for (int j = 0; j < 4; ++j)
      for (int k = 0; k < 4; ++k) graded.updateNode(-0.35 + 0.1 * i, 0.05 + 0.1 * j, -0.35 + 0.1 * k, true);
  for (int i = 0; i < 6; ++i) {
    for (int n = 0; n <= i; ++n) graded.updateNode(1.05 + 0.1 * i, -1.05, 0.55, n % 3 != 2);
  }
  graded.updateNode(-2.05, 2.05, -0.05, false);
  graded.prune();
  auto geb = mapmerge::read_octree_file(std::string(MAPMERGE_DATA_DIR) + "/geb079.bt");
  std::size_t i = 0;  // every 5th occupied leaf one miss (still occupied), every 11th three (free)
  std::vector<octomap::OcTreeKey> missed, emptied;
  for (auto it = geb->begin_leafs(), end = geb->end_leafs(); it != end; ++it, ++i) {
    if (!geb->isNodeOccupied(*it) || it.getDepth() != geb->getTreeDepth()) continue;
    if (i % 11 == 0) emptied.push_back(it.getKey());
    else if (i % 5 == 0) missed.push_back(it.getKey());
  }
  for (const auto& k : missed) geb->updateNode(k, false);
  for (const auto& k : emptied)
    for (int n = 0; n < 3; ++n) geb->updateNode(k, false);
  ASSERT_GT(missed.size(), 100U);
  for (const auto& [tree, threshold] : {std::pair<const octomap::OcTree*, float>{&graded, 0.8F}, {geb.get(), 0.96F}}) {
    const auto ot = mapmerge::encode_map(*tree, mapmerge::Encoding::kOctomapOt);
    const mapmerge::CheckedMap c = mapmerge::check_map(ot.data(), ot.size(), mapmerge::Encoding::kOctomapOt, {});
    ASSERT_TRUE(c.ok() && c.map) << c.reason;
    const auto& held = c.map;
    ASSERT_TRUE(held->full_body());
    expect_same_points(ma::to_points(*held, {}), ma::to_points(*tree, {}));
    ma::ToPointsConfig sure;
    sure.min_occupancy = threshold;  // leaves below it are dropped, each by its own occupancy
    const auto fewer = ma::to_points(*held, sure);
    expect_same_points(fewer, ma::to_points(*tree, sure));
    EXPECT_LT(fewer.size(), ma::to_points(*tree, {}).size());
    EXPECT_GT(fewer.size(), 0U);
    for (const auto state : {mapmerge::LeafState::kOccupied, mapmerge::LeafState::kFree}) {
      const mapmerge::LeafSet a = mapmerge::LeafSet::of(*held, state), b = mapmerge::LeafSet::of(*tree, state);
      ASSERT_EQ(a.size(), b.size());
      ASSERT_GT(a.size(), 0U);
      for (std::size_t k = 0; k < a.size(); ++k) ASSERT_EQ(a.centre(k), b.centre(k)) << k;
    }
    const Eigen::AlignedBox3d box = mapmerge::leaf_bounds(*held), tree_box = mapmerge::leaf_bounds(*tree);
    EXPECT_EQ(box.min(), tree_box.min());
    EXPECT_EQ(box.max(), tree_box.max());
    EXPECT_FALSE(held->has_tree()) << "read off the body";
  }
}

TEST(Fitness, HandComputedCase) {
  // Pairs at 0.01, 0.02, 0.5 and 0.03 m; d_th 0.1: the 0.5 m pair has weight 0 (Eq. 7).
  const std::vector<double> d{0.01, 0.02, 0.5, 0.03};
  const ma::Fitness f = ma::fitness_from_distances(d, 0.1, 3);
  EXPECT_EQ(f.n_w, 3U);
  EXPECT_NEAR(f.value, (0.01 + 0.02 + 0.03) / 3.0, 1e-12);
  // n_w < n_th: +inf (Eq. 6).
  EXPECT_TRUE(std::isinf(ma::fitness_from_distances(d, 0.1, 4).value));
  EXPECT_TRUE(std::isinf(ma::fitness_from_distances({}, 0.1, 0).value));
}

TEST(Fitness, NearestNeighbourPairs) {
  const std::vector<Eigen::Vector3f> target{{0, 0, 0}, {1, 0, 0}, {0, 1, 0}};
  const std::vector<Eigen::Vector3f> source{{0.01F, 0, 0}, {1, 0.02F, 0}, {5, 5, 5}, {0, 1.04F, 0}};
  const ma::Fitness f = ma::fitness_score(source, target, 0.05, 2);
  EXPECT_EQ(f.n_w, 3U);
  EXPECT_NEAR(f.value, (0.01 + 0.02 + 0.04) / 3.0, 1e-6);
}

/// A flat 2 m x 2 m floor (grid spacing h) with a box of 0.2 x 0.3 x 0.24 m standing on
/// [0.9, 1.1] x [0.9, 1.2] (no symmetry, so no ties between equally salient points).
std::vector<Eigen::Vector3f> floor_with_box(float h) {
  std::vector<Eigen::Vector3f> pts;
  const int n = static_cast<int>(std::lround(2.0F / h));
  const int x0 = static_cast<int>(std::lround(0.9F / h)), x1 = static_cast<int>(std::lround(1.1F / h));
  const int y0 = x0, y1 = static_cast<int>(std::lround(1.2F / h));
  const int top = static_cast<int>(std::lround(0.24F / h));
  for (int i = 0; i <= n; ++i)
    for (int j = 0; j <= n; ++j) {
      const bool under_box = i > x0 && i < x1 && j > y0 && j < y1;
      if (!under_box) pts.emplace_back(i * h, j * h, 0.0F);
    }
  for (int i = x0; i <= x1; ++i)
    for (int j = y0; j <= y1; ++j)
      for (int k = 1; k <= top; ++k) {
        const bool surface = i == x0 || i == x1 || j == y0 || j == y1 || k == top;
        if (surface) pts.emplace_back(i * h, j * h, k * h);
      }
  return pts;
}

ma::KeypointConfig iss_config() {
  ma::KeypointConfig c;
  c.salient_radius = 6.0;  // x res (res = h)
  c.non_max_radius = 4.0;
  c.gamma_21 = 0.975;
  c.gamma_32 = 0.975;
  c.min_neighbors = 5;
  return c;
}

TEST(Iss, FlatSurfaceHasNoKeypointsTheBoxHas) {
  const float h = 0.02F;
  const auto pts = floor_with_box(h);
  const auto kp = ma::iss_keypoints(pts, iss_config(), h);
  ASSERT_FALSE(kp.empty());
  const Eigen::Vector2f centre(1.0F, 1.05F);
  std::size_t near_box = 0;
  for (std::size_t idx : kp) {
    const Eigen::Vector3f& p = pts[idx];
    // Distance to the box footprint (0.9..1.1) and to the floor's outer border.
    const float dx = std::max(0.0F, std::abs(p.x() - centre.x()) - 0.1F);
    const float dy = std::max(0.0F, std::abs(p.y() - centre.y()) - 0.15F);
    const float to_box = std::hypot(dx, dy);
    const float to_border = std::min({p.x(), p.y(), 2.0F - p.x(), 2.0F - p.y()});
    // Eq. 3: on a plane lambda2/lambda1 is ~1, above gamma_21, so the open floor has none.
    EXPECT_TRUE(to_box < 7 * h || to_border < 7 * h) << "keypoint on the flat floor at " << p.transpose();
    near_box += to_box < 7 * h ? 1 : 0;
  }
  EXPECT_GT(near_box, 0U);
}

TEST(Iss, KeypointsMoveWithTheShape) {
  const float h = 0.02F;
  const auto pts = floor_with_box(h);
  const ma::KeypointConfig c = iss_config();
  const auto kp = ma::iss_keypoints(pts, c, h);
  // Rotated by 30 degrees about z and shifted: the scatter matrices' eigenvalues do not change.
  const Eigen::Affine3f T = Eigen::Translation3f(3.0F, -1.0F, 0.5F) *
                            Eigen::AngleAxisf(0.5236F, Eigen::Vector3f::UnitZ());
  std::vector<Eigen::Vector3f> moved;
  for (const auto& p : pts) moved.push_back(T * p);
  const auto kp_moved = ma::iss_keypoints(moved, c, h);
  // Ties between symmetric points may break differently after rounding: compare positions.
  std::size_t same = 0;
  for (std::size_t i : kp) {
    bool found = false;
    for (std::size_t j : kp_moved) found = found || (moved[j] - T * pts[i]).norm() < 3 * h;
    same += found ? 1 : 0;
  }
  EXPECT_GE(same * 10, kp.size() * 7) << same << " of " << kp.size();
}

TEST(Submodels, SpiralFromTheBorderCoversEveryPoint) {
  std::vector<Eigen::Vector3f> pts;
  for (int i = 0; i < 100; ++i)
    for (int j = 0; j < 100; ++j) pts.emplace_back(i * 0.1F, j * 0.1F, 0.0F);
  ma::SubmodelConfig c;
  c.block_size = 20.0;  // 2 m at 0.1 m
  c.block_overlap = 0.0;
  const auto blocks = ma::make_submodels(pts, c, 0.1);
  ASSERT_EQ(blocks.size(), 25U);  // 10 m / 2 m = 5 x 5
  std::vector<int> seen(pts.size(), 0);
  for (const auto& b : blocks)
    for (std::size_t m : b.members) ++seen[m];
  for (int s : seen) EXPECT_EQ(s, 1);
  // The first 16 blocks form the outer ring, the centre block comes last.
  auto on_border = [](const ma::Block& b) {
    return b.min.x() < 0.5F || b.min.y() < 0.5F || b.max.x() > 9.5F || b.max.y() > 9.5F;
  };
  for (std::size_t i = 0; i < 16; ++i) EXPECT_TRUE(on_border(blocks[i])) << i;
  for (std::size_t i = 16; i < 25; ++i) EXPECT_FALSE(on_border(blocks[i])) << i;
  EXPECT_NEAR(blocks.back().min.x(), 4.0F, 1e-4F);
  EXPECT_NEAR(blocks.back().min.y(), 4.0F, 1e-4F);
  // With overlap, points are shared by neighbouring blocks.
  c.block_overlap = 0.5;
  std::size_t members = 0;
  for (const auto& b : ma::make_submodels(pts, c, 0.1)) members += b.members.size();
  EXPECT_GT(members, 2 * pts.size());
}

TEST(CropAndTransform, BoxLargerThanTheMapKeepsEveryVoxel) {
  // The bench's z slab and "everything" boxes reach far outside the octree's key range.
  const auto tree = mapmerge::read_octree_file(std::string(MAPMERGE_DATA_DIR) + "/geb079.bt");
  const Eigen::AlignedBox3d all(Eigen::Vector3d::Constant(-1e6), Eigen::Vector3d::Constant(1e6));
  const auto copy = mapmerge::crop_and_transform(*tree, all, Eigen::Isometry3d::Identity());
  EXPECT_EQ(mapmerge::count_occupied(*copy, all), mapmerge::count_occupied(*tree, all));
  const Eigen::AlignedBox3d slab(Eigen::Vector3d(-1e6, -1e6, 0.0), Eigen::Vector3d(1e6, 1e6, 1.0));
  const auto part = mapmerge::crop_and_transform(*tree, slab, Eigen::Isometry3d::Identity());
  EXPECT_EQ(mapmerge::count_occupied(*part, all), mapmerge::count_occupied(*tree, slab));
  EXPECT_GT(mapmerge::count_occupied(*part, all), 0U);
  const Eigen::AlignedBox3d far(Eigen::Vector3d::Constant(1e5), Eigen::Vector3d::Constant(1e6));
  EXPECT_EQ(mapmerge::crop_and_transform(*tree, far, Eigen::Isometry3d::Identity())->size(), 0U);
}

TEST(CropAndTransform, AnOverlapCutsPartsShareThatShareOfTheOccupiedVoxels) {
  const auto tree = mapmerge::read_octree_file(std::string(MAPMERGE_DATA_DIR) + "/geb079.bt");
  const Eigen::AlignedBox3d all(Eigen::Vector3d::Constant(-1e6), Eigen::Vector3d::Constant(1e6));
  const auto total = static_cast<double>(mapmerge::count_occupied(*tree, all));
  for (const int axis : {0, 1}) {
    for (const double share : {0.1, 0.3}) {
      const auto [below, above] = mapmerge::overlap_cut(*tree, axis, share);
      ASSERT_LT(above.min()(axis), below.max()(axis));
      const Eigen::AlignedBox3d both = below.intersection(above);
      // To within the layer of voxels at a cut (a wall across the corridor: up to ~2 % here).
      constexpr double kLayer = 0.03;
      EXPECT_NEAR(static_cast<double>(mapmerge::count_occupied(*tree, both)) / total, share, kLayer);
      // The parts are the map below the second cut and above the first: equal halves of the rest.
      EXPECT_NEAR(static_cast<double>(mapmerge::count_occupied(*tree, below)) / total, (1.0 + share) / 2, kLayer);
      EXPECT_NEAR(static_cast<double>(mapmerge::count_occupied(*tree, above)) / total, (1.0 + share) / 2, kLayer);
    }
  }
  EXPECT_THROW(mapmerge::overlap_cut(*tree, 3, 0.1), std::invalid_argument);
  EXPECT_THROW(mapmerge::overlap_cut(*tree, 0, 1.5), std::invalid_argument);
}

namespace {

/// The occupied voxel centres of a real map, each moved by `T`.
std::vector<Eigen::Vector3f> map_points(const std::string& file, const Eigen::Affine3f& T = Eigen::Affine3f::Identity()) {
  const auto tree = mapmerge::read_octree_file(std::string(MAPMERGE_DATA_DIR) + "/" + file);
  std::vector<Eigen::Vector3f> out;
  for (const auto& p : ma::to_points(*tree, {})) out.push_back(T * p.position);
  return out;
}

float quantile_z(std::vector<Eigen::Vector3f> points, double q) {
  const auto k = static_cast<std::size_t>(q * static_cast<double>(points.size() - 1));
  std::nth_element(points.begin(), points.begin() + static_cast<std::ptrdiff_t>(k), points.end(),
                   [](const Eigen::Vector3f& a, const Eigen::Vector3f& b) { return a.z() < b.z(); });
  return points[k].z();
}

}  // namespace

TEST(Ground, ACorridorsFloorIsTheGroundTheSameEveryTime) {
  const auto points = map_points("geb079.bt");
  const auto ground = ma::ground_points(points, {}, 0.08);
  ASSERT_GT(ground.size(), points.size() / 10);  // a corridor's floor is a large share of it
  std::vector<Eigen::Vector3f> floor;
  for (const std::size_t i : ground) floor.push_back(points[i]);
  // The lowest layer of the map: the floor's middle is at the map's bottom, and every ground
  // point is within ground_distance (1.5 x 8 cm) of a plane at most 10 deg from level.
  EXPECT_NEAR(quantile_z(floor, 0.5), quantile_z(points, 0.05), 0.1);
  EXPECT_LT(quantile_z(floor, 1.0), quantile_z(points, 0.5));
  EXPECT_EQ(ma::ground_points(points, {}, 0.08), ground);  // one RANSAC thread: deterministic
}

TEST(Ground, ACeilingIsNotTheGround) {
  const Eigen::Affine3f upside_down(Eigen::AngleAxisf(static_cast<float>(M_PI), Eigen::Vector3f::UnitX()));
  EXPECT_TRUE(ma::ground_points(map_points("geb079.bt", upside_down), {}, 0.08).empty());
  EXPECT_TRUE(ma::ground_points(map_points("fr_078_tidyup.bt", upside_down), {}, 0.05).empty());
}

TEST(Ground, ATiltedFloorIsGroundWithinTheTiltLimitOnly) {
  const auto level = ma::ground_points(map_points("geb079.bt"), {}, 0.08);
  const auto tilted = map_points("geb079.bt", Eigen::Affine3f(Eigen::AngleAxisf(static_cast<float>(5.0 * M_PI / 180.0),
                                                                                  Eigen::Vector3f::UnitX())));
  ma::PreprocessConfig c;  // 10 deg
  EXPECT_NEAR(static_cast<double>(ma::ground_points(tilted, c, 0.08).size()), static_cast<double>(level.size()),
              0.01 * static_cast<double>(level.size()));
  c.ground_max_tilt_deg = 2.0;
  EXPECT_LT(ma::ground_points(tilted, c, 0.08).size(), level.size() / 2);
}
