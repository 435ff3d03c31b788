// Fusion (stage 9): log-odds added and clamped, real maps cut and fused back, resolutions mixed.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <random>

#include <Eigen/Geometry>

#include "map_test_util.hpp"
#include "mapmerge/map/crop.hpp"
#include "mapmerge/map/fusion.hpp"
#include "mapmerge/map/map_codec.hpp"

namespace mapmerge {
namespace {

Eigen::Matrix4d pose(double yaw, const Eigen::Vector3d& t) {
  Eigen::Matrix4d T = Eigen::Matrix4d::Identity();
  T.topLeftCorner<3, 3>() = Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  T.topRightCorner<3, 1>() = t;
  return T;
}

/// The leaves of `tree` whose centre x is in [x_min, x_max), as a new tree in the same frame.
std::unique_ptr<octomap::OcTree> cut(const octomap::OcTree& tree, double x_min, double x_max) {
  auto part = std::make_unique<octomap::OcTree>(tree.getResolution());
  for (auto it = tree.begin_leafs(), end = tree.end_leafs(); it != end; ++it) {
    if (it.getX() < x_min || it.getX() >= x_max) continue;
    const int n = 1 << (16 - it.getDepth());  // expand pruned leaves to full resolution
    const octomap::OcTreeKey base = it.getIndexKey();
    for (int i = 0; i < n * n * n; ++i) {
      const octomap::OcTreeKey k(base[0] + i % n, base[1] + (i / n) % n, base[2] + i / (n * n));
      part->setNodeValue(k, it->getLogOdds(), true);
    }
  }
  part->updateInnerOccupancy();
  part->prune();
  return part;
}

/// Occupied full-resolution voxel centres of `tree`.
std::vector<octomap::point3d> occupied_centres(const octomap::OcTree& tree) {
  std::vector<octomap::point3d> centres;
  const double res = tree.getResolution();
  for (auto it = tree.begin_leafs(), end = tree.end_leafs(); it != end; ++it) {
    if (!tree.isNodeOccupied(*it)) continue;
    const int n = 1 << (16 - it.getDepth());
    const octomap::point3d corner = it.getCoordinate() - octomap::point3d(1, 1, 1) *
                                                             static_cast<float>(0.5 * it.getSize());
    for (int i = 0; i < n * n * n; ++i) {
      centres.push_back(corner + octomap::point3d(static_cast<float>((i % n + 0.5) * res),
                                                  static_cast<float>(((i / n) % n + 0.5) * res),
                                                  static_cast<float>((i / (n * n) + 0.5) * res)));
    }
  }
  return centres;
}

/// Share of `points` (moved by T) that fall on an occupied voxel of `tree`.
double occupied_share(const octomap::OcTree& tree, const std::vector<octomap::point3d>& points,
                      const Eigen::Matrix4d& T) {
  std::size_t hits = 0;
  for (const auto& p : points) {
    const Eigen::Vector3d q = T.topLeftCorner<3, 3>() * Eigen::Vector3d(p.x(), p.y(), p.z()) +
                              T.topRightCorner<3, 1>();
    const octomap::OcTreeNode* node = tree.search(q.x(), q.y(), q.z());
    hits += node != nullptr && tree.isNodeOccupied(node);
  }
  return points.empty() ? 0.0 : static_cast<double>(hits) / static_cast<double>(points.size());
}

/// Full-resolution voxels that are occupied (or free) in `tree`.
std::size_t voxel_count(const octomap::OcTree& tree, bool occupied) {
  std::size_t n = 0;
  for (auto it = tree.begin_leafs(), end = tree.end_leafs(); it != end; ++it) {
    if (tree.isNodeOccupied(*it) == occupied) n += std::size_t{1} << (3 * (16 - it.getDepth()));
  }
  return n;
}

octomap::OcTreeKey first_leaf_key(const octomap::OcTree& tree, bool occupied) {
  for (auto it = tree.begin_leafs(16), end = tree.end_leafs(); it != end; ++it) {
    if (it.getDepth() == 16 && tree.isNodeOccupied(*it) == occupied) return it.getKey();
  }
  ADD_FAILURE() << "no such leaf";
  return {};
}

TEST(Fusion, AddsLogOddsAndClampsOnRealVoxels) {
  auto target = test::load("geb079.bt");
  const float max = target->getClampingThresMaxLog();  // logodds(0.971) = 3.51
  const float min = target->getClampingThresMinLog();  // logodds(0.1192) = -1.99
  const octomap::OcTreeKey occupied = first_leaf_key(*target, true);
  const octomap::OcTreeKey free = first_leaf_key(*target, false);
  octomap::OcTreeKey unknown = occupied;
  unknown[2] = static_cast<octomap::key_type>(unknown[2] + 2000);  // 160 m above: never mapped
  ASSERT_EQ(target->search(unknown), nullptr);
  ASSERT_FLOAT_EQ(target->search(occupied)->getLogOdds(), max);
  ASSERT_FLOAT_EQ(target->search(free)->getLogOdds(), min);

  octomap::OcTree source(target->getResolution());
  source.setNodeValue(occupied, -1.0F);  // weakens the occupied voxel: 3.51 - 1.0
  source.setNodeValue(free, 0.5F);       // weakens the free voxel: -1.99 + 0.5
  source.setNodeValue(unknown, 0.7F);    // unknown (0) + 0.7
  const FuseResult r = fuse_into(*target, source, Eigen::Matrix4d::Identity(), FuseConfig{});
  ASSERT_TRUE(r.ok) << r.reason;
  EXPECT_EQ(r.source_leaves, 3U);
  EXPECT_NEAR(target->search(occupied)->getLogOdds(), max - 1.0F, 1e-5);
  EXPECT_NEAR(target->search(free)->getLogOdds(), min + 0.5F, 1e-5);
  EXPECT_NEAR(target->search(unknown)->getLogOdds(), 0.7F, 1e-5);

  // Adding more evidence clamps at the thresholds instead of accumulating without bound.
  octomap::OcTree strong(target->getResolution());
  strong.setNodeValue(occupied, 5.0F);
  strong.setNodeValue(free, -5.0F);
  ASSERT_TRUE(fuse_into(*target, strong, Eigen::Matrix4d::Identity(), FuseConfig{}).ok);
  EXPECT_FLOAT_EQ(target->search(occupied)->getLogOdds(), max);
  EXPECT_FLOAT_EQ(target->search(free)->getLogOdds(), min);
}

TEST(Fusion, FreeSpaceIsFusedUnlessDisabled) {
  auto target = test::load("geb079.bt");
  const octomap::OcTreeKey occupied = first_leaf_key(*target, true);
  octomap::OcTree source(target->getResolution());
  source.setNodeValue(occupied, -1.5F);  // free evidence on an occupied voxel
  FuseConfig config;
  config.fuse_free = false;
  ASSERT_TRUE(fuse_into(*target, source, Eigen::Matrix4d::Identity(), config).ok);
  EXPECT_TRUE(target->isNodeOccupied(target->search(occupied)));
  config.fuse_free = true;
  ASSERT_TRUE(fuse_into(*target, source, Eigen::Matrix4d::Identity(), config).ok);
  EXPECT_NEAR(target->search(occupied)->getLogOdds(), target->getClampingThresMaxLog() - 1.5F,
              1e-5);
}

TEST(Fusion, IdentityIntoEmptyReproducesTheMapExactly) {
  const auto source = test::load("geb079.bt");
  octomap::OcTree target(source->getResolution());
  const FuseResult r = fuse_into(target, *source, Eigen::Matrix4d::Identity(), FuseConfig{});
  ASSERT_TRUE(r.ok) << r.reason;
  EXPECT_GT(r.block_updates, 0U);  // pruned leaves went in whole
  EXPECT_EQ(encode_map(target, Encoding::kOctomapBt), encode_map(*source, Encoding::kOctomapBt));
}

TEST(Fusion, FusingAMapWithItselfKeepsItsOccupancy) {
  const auto source = test::load("geb079.bt");
  auto target = test::load("geb079.bt");
  ASSERT_TRUE(fuse_into(*target, *source, Eigen::Matrix4d::Identity(), FuseConfig{}).ok);
  EXPECT_EQ(encode_map(*target, Encoding::kOctomapBt), encode_map(*source, Encoding::kOctomapBt));
}

TEST(Fusion, RealMapCutInTwoAndMovedIsFusedBackToTheOriginal) {
  const auto original = test::load("fr_079.bt");
  double min_x = 0, min_y = 0, min_z = 0, max_x = 0, max_y = 0, max_z = 0;
  original->getMetricMin(min_x, min_y, min_z);
  original->getMetricMax(max_x, max_y, max_z);
  const double mid = 0.5 * (min_x + max_x);
  const auto left = cut(*original, min_x - 1, mid + 2.0);  // 4 m overlap
  const auto right = cut(*original, mid - 2.0, max_x + 1);
  // The right part as a robot would have it: in its own frame, unknown to the other robot.
  const Eigen::Matrix4d T_global_right = pose(2.2, Eigen::Vector3d(4.0, -7.5, 0.3));
  octomap::OcTree right_local(original->getResolution());
  ASSERT_TRUE(fuse_into(right_local, *right, T_global_right.inverse(), FuseConfig{}).ok);

  FuseConfig config;
  octomap::OcTree fused(original->getResolution());
  ASSERT_TRUE(fuse_into(fused, *left, Eigen::Matrix4d::Identity(), config).ok);
  ASSERT_TRUE(fuse_into(fused, right_local, T_global_right, config).ok);

  // Every occupied voxel of the original is occupied again (two rotated resamplings of the right
  // part may move a voxel by one cell: check within a voxel's reach), and nothing much is added.
  const auto original_occ = occupied_centres(*original);
  const auto fused_occ = occupied_centres(fused);
  const double recall = occupied_share(fused, original_occ, Eigen::Matrix4d::Identity());
  const double precision = occupied_share(*original, fused_occ, Eigen::Matrix4d::Identity());
  std::printf("recall %.3f precision %.3f (original %zu, fused %zu occupied voxels)\n", recall,
              precision, original_occ.size(), fused_occ.size());
  EXPECT_GT(recall, 0.92);
  EXPECT_GT(precision, 0.92);
  EXPECT_NEAR(static_cast<double>(fused_occ.size()) / static_cast<double>(original_occ.size()), 1.0,
              0.15);
  // The left part, fused with the identity, is exact.
  const auto left_occ = occupied_centres(*left);
  EXPECT_DOUBLE_EQ(occupied_share(fused, left_occ, Eigen::Matrix4d::Identity()), 1.0);
}

TEST(Fusion, QuarterTurnsAndWholeVoxelShiftsAreExact) {
  const auto source = test::load("geb079.bt");
  const double res = source->getResolution();
  const Eigen::Matrix4d T = pose(M_PI / 2, Eigen::Vector3d(37 * res, -12 * res, 3 * res));
  octomap::OcTree target(res);
  ASSERT_TRUE(fuse_into(target, *source, T, FuseConfig{}).ok);
  const auto occ = occupied_centres(*source);
  EXPECT_DOUBLE_EQ(occupied_share(target, occ, T), 1.0);
  EXPECT_EQ(occupied_centres(target).size(), occ.size());
  EXPECT_EQ(voxel_count(target, false), voxel_count(*source, false));  // free space too
}

/// Every target voxel gets the value of the source leaf its centre lies in (half-open cubes),
/// checked voxel by voxel against the source for leaves of 1 to 16 voxels under random turns.
TEST(Fusion, EachTargetVoxelTakesTheSourceLeafItsCentreLiesInUnderAnyTurn) {
  const double res = 0.1;
  octomap::OcTree source(res);
  const auto put_block = [&](int x, int y, int z, int n, float v) {  // n^3 voxels at an aligned key
    for (int i = 0; i < n; ++i)
      for (int j = 0; j < n; ++j)
        for (int k = 0; k < n; ++k) {
          source.setNodeValue(octomap::OcTreeKey(32768 + x + i, 32768 + y + j, 32768 + z + k), v);
        }
  };
  put_block(0, 0, 0, 16, 1.5F);
  put_block(16, 0, 0, 8, -1.0F);
  put_block(16, 8, 0, 4, 2.5F);
  put_block(-4, -4, -4, 2, 0.7F);
  put_block(-1, 5, 3, 1, 3.0F);
  put_block(-2, 5, 3, 1, -0.4F);
  source.prune();
  ASSERT_LT(source.getNumLeafNodes(), 100u);  // big pruned cubes, not voxels
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> angle(-M_PI, M_PI), shift(-0.37, 0.37);
  FuseConfig config;
  for (int trial = 0; trial < 6; ++trial) {
    const Eigen::Vector3d axis = Eigen::Vector3d(angle(rng), angle(rng), angle(rng)).normalized();
    const Eigen::Matrix3d R = trial == 0 ? Eigen::Matrix3d(Eigen::AngleAxisd(angle(rng), Eigen::Vector3d::UnitZ()))
                                         : Eigen::Matrix3d(Eigen::AngleAxisd(angle(rng), axis));
    Eigen::Matrix4d T = Eigen::Matrix4d::Identity();
    T.topLeftCorner<3, 3>() = R;
    T.topRightCorner<3, 1>() = Eigen::Vector3d(shift(rng), shift(rng), shift(rng));
    octomap::OcTree target(res);
    ASSERT_TRUE(fuse_into(target, source, T, config).ok);
    const Eigen::Matrix4d T_inv = T.inverse();
    std::size_t known = 0;
    for (int x = -50; x < 50; ++x)
      for (int y = -50; y < 50; ++y)
        for (int z = -50; z < 50; ++z) {
          const octomap::OcTreeKey key(32768 + x, 32768 + y, 32768 + z);
          const octomap::point3d c = target.keyToCoord(key);
          const Eigen::Vector3d q = (T_inv * Eigen::Vector4d(c.x(), c.y(), c.z(), 1.0)).head<3>();
          const octomap::OcTreeNode* want = source.search(q.x(), q.y(), q.z());
          const octomap::OcTreeNode* got = target.search(key);
          ASSERT_EQ(got != nullptr, want != nullptr) << "trial " << trial << " voxel " << x << " " << y << " " << z;
          if (want == nullptr) continue;
          ++known;
          ASSERT_FLOAT_EQ(got->getLogOdds(), want->getLogOdds()) << "trial " << trial << " voxel " << x << " " << y << " " << z;
        }
    EXPECT_GT(known, 4500u) << "trial " << trial;  // ~16^3 + 8^3 + ... voxels' worth of space
  }
}

TEST(Fusion, CoarserSourceIntoFinerTarget) {
  const auto source = test::load("geb079.bt");  // 8 cm
  octomap::OcTree target(0.05);
  ASSERT_TRUE(fuse_into(target, *source, pose(0.3, Eigen::Vector3d(0.1, 0.2, 0)), FuseConfig{}).ok);
  const auto src_occ = occupied_centres(*source);
  const auto dst_occ = occupied_centres(target);
  // Occupied volume is preserved (0.08^3 per source voxel, 0.05^3 per target voxel).
  const double src_volume = static_cast<double>(src_occ.size()) * std::pow(0.08, 3);
  const double dst_volume = static_cast<double>(dst_occ.size()) * std::pow(0.05, 3);
  EXPECT_NEAR(dst_volume / src_volume, 1.0, 0.1);
  EXPECT_GT(occupied_share(target, src_occ, pose(0.3, Eigen::Vector3d(0.1, 0.2, 0))), 0.95);
}

TEST(Fusion, RefineSplitsEveryVoxelOntoTheFinerGrid) {
  // mapmerge::refine (the bench's 2 cm grid): geb079's 8 cm voxels onto a 4 cm grid, which
  // splits each into exactly 8; every fine voxel keeps the state of the coarse one it lies in.
  const auto source = test::load("geb079.bt");
  const auto fine = refine(*source, 0.04);
  ASSERT_NEAR(fine->getResolution(), 0.04, 1e-12);
  const Eigen::AlignedBox3d all(Eigen::Vector3d::Constant(-1e4), Eigen::Vector3d::Constant(1e4));
  EXPECT_EQ(count_occupied(*fine, all), 8 * count_occupied(*source, all));
  std::size_t checked = 0;
  for (auto it = fine->begin_leafs(), end = fine->end_leafs(); it != end && checked < 20000; ++it, ++checked) {
    const octomap::OcTreeNode* coarse = source->search(it.getCoordinate());
    ASSERT_NE(coarse, nullptr);
    EXPECT_EQ(fine->isNodeOccupied(*it), source->isNodeOccupied(coarse));
  }
  EXPECT_THROW(refine(*source, 0.1), std::invalid_argument);
  EXPECT_THROW(refine(*source, 0.0), std::invalid_argument);
}

TEST(Fusion, FinerSourceIntoCoarserTargetKeepsEveryOccupiedVoxel) {
  const auto source = test::load("fr_078_tidyup.bt");  // 5 cm
  octomap::OcTree target(0.2);
  const Eigen::Matrix4d T = pose(-0.7, Eigen::Vector3d(1.0, 0.0, 0.4));
  const FuseResult r = fuse_into(target, *source, T, FuseConfig{});
  ASSERT_TRUE(r.ok) << r.reason;
  // Occupied wins within a coarse voxel (OctoMap's max-of-children rule): none is lost.
  std::vector<octomap::point3d> src_occ;
  for (auto it = source->begin_leafs(), end = source->end_leafs(); it != end; ++it) {
    if (source->isNodeOccupied(*it) && it.getDepth() == 16) src_occ.push_back(it.getCoordinate());
  }
  EXPECT_DOUBLE_EQ(occupied_share(target, src_occ, T), 1.0);
  EXPECT_LT(target.getNumLeafNodes(), source->getNumLeafNodes() / 8);
}

TEST(Fusion, NonRigidTransformIsRejectedAndTargetUntouched) {
  const auto source = test::load("geb079.bt");
  octomap::OcTree target(0.08);
  Eigen::Matrix4d scale = Eigen::Matrix4d::Identity();
  scale(0, 0) = 2.0;
  FuseResult r = fuse_into(target, *source, scale, FuseConfig{});
  EXPECT_FALSE(r.ok);
  EXPECT_FALSE(r.reason.empty());
  Eigen::Matrix4d mirror = Eigen::Matrix4d::Identity();
  mirror(2, 2) = -1.0;
  EXPECT_FALSE(fuse_into(target, *source, mirror, FuseConfig{}).ok);
  Eigen::Matrix4d nan = Eigen::Matrix4d::Identity();
  nan(0, 3) = std::nan("");
  EXPECT_FALSE(fuse_into(target, *source, nan, FuseConfig{}).ok);
  EXPECT_EQ(target.size(), 0U);
  EXPECT_THROW(fuse_maps({{source.get(), scale}}, 0.08), MapError);
}

TEST(Fusion, SourceWithAHugeLeafIsRefusedBeforeAnyWork) {
  // A valid two-byte map: one free leaf 1.6 km wide. Rotated, it would touch ~10^10 voxels.
  DecodeLimits limits;
  limits.max_fusion_work = 1e12;  // let it through decoding: fusion must defend itself too
  const DecodeResult huge = decode_tree_body("OcTree", 0.05, true, {0x01, 0x00}, limits);
  ASSERT_TRUE(huge.ok()) << huge.reason;
  auto target = test::load("geb079.bt");
  const std::size_t before = target->size();
  const FuseResult r = fuse_into(*target, *huge.tree, pose(0.4, Eigen::Vector3d(1, 2, 0)), FuseConfig{});
  EXPECT_FALSE(r.ok);
  EXPECT_NE(r.reason.find("max_work"), std::string::npos) << r.reason;
  EXPECT_EQ(target->size(), before);
}

TEST(Fusion, FuseMapsRecordsWhichRobotContributedEachVoxel) {
  const auto original = test::load("geb079.bt");
  double min_x = 0, min_y = 0, min_z = 0, max_x = 0, max_y = 0, max_z = 0;
  original->getMetricMin(min_x, min_y, min_z);
  original->getMetricMax(max_x, max_y, max_z);
  const double mid = 0.5 * (min_x + max_x);
  const auto left = cut(*original, min_x - 1, mid);
  const auto right = cut(*original, mid, max_x + 1);
  const Eigen::Matrix4d I = Eigen::Matrix4d::Identity();
  FusedMap fused = fuse_maps_with_provenance({{left.get(), I}, {right.get(), I}}, 0.08);
  ASSERT_TRUE(fused.tree);
  EXPECT_EQ(encode_map(*fused.tree, Encoding::kOctomapBt), encode_map(*original, Encoding::kOctomapBt));
  ASSERT_EQ(fused.provenance.robots.size(), 2U);
  std::size_t checked = 0;
  for (const auto& [key, owner] : fused.provenance.owner) {
    const octomap::OcTreeNode* in_left = left->search(key);
    EXPECT_EQ(owner.robot, in_left != nullptr && left->isNodeOccupied(in_left) ? 0 : 1);
    ++checked;
  }
  EXPECT_EQ(checked, occupied_centres(*original).size());
  EXPECT_EQ(fuse_maps({{left.get(), I}, {right.get(), I}}, 0.08)->size(), fused.tree->size());

  const std::string path = ::testing::TempDir() + "/fused.prov";
  fused.provenance.robots[1].name = "robot-2";
  write_provenance(fused.provenance, path);
  const Provenance back = read_provenance(path);
  EXPECT_DOUBLE_EQ(back.resolution, 0.08);
  ASSERT_EQ(back.robots.size(), 2U);
  EXPECT_EQ(back.robots[1].name, "robot-2");
  EXPECT_EQ(back.owner.size(), fused.provenance.owner.size());
  for (const auto& [key, owner] : fused.provenance.owner) {
    ASSERT_EQ(back.owner.at(key).robot, owner.robot);
  }
  EXPECT_THROW(read_provenance(test::data_path("geb079.bt")), MapError);
}

}  // namespace
}  // namespace mapmerge
