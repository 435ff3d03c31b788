// Incremental global fusion: after any sequence of map updates, pose changes and removals, the
// global map equals a from-scratch fusion of the final maps, voxel by voxel. Real maps from data/.
#include <gtest/gtest.h>

#include <random>
#include <set>

#include <Eigen/Geometry>

#include "map_test_util.hpp"
#include "mapmerge/map/bounds.hpp"
#include "mapmerge/map/crop.hpp"
#include "mapmerge/map/global_delta.hpp"
#include "mapmerge/map/global_fusion.hpp"
#include "mapmerge/map/map_codec.hpp"

namespace mapmerge {
namespace {

using Tree = std::shared_ptr<const octomap::OcTree>;

struct Robot {
  std::string id;
  Eigen::Isometry3d T_robot_world;  ///< the robot's own (unknown) frame
  Tree map;
};

/// The part of `world` between x0 and x1, in a frame turned by `yaw` and moved.
Robot cut(const octomap::OcTree& world, const std::string& id, double x0, double x1, double yaw) {
  double a[3];
  double b[3];
  world.getMetricMin(a[0], a[1], a[2]);
  world.getMetricMax(b[0], b[1], b[2]);
  const Eigen::AlignedBox3d box(Eigen::Vector3d(x0, a[1], a[2]), Eigen::Vector3d(x1, b[1], b[2]));
  const Eigen::Isometry3d T = make_transform(1.3 * yaw, -0.7 * yaw, 0.1, 0.0, 0.0, yaw);
  return Robot{id, T, Tree(crop_and_transform(world, box, T))};
}

Eigen::Matrix4d T_global(const Robot& r) { return r.T_robot_world.inverse().matrix(); }

/// Every leaf of two canonical (pruned) trees: same keys, same depths, same log-odds.
void expect_same_voxels(const octomap::OcTree& a, const octomap::OcTree& b) {
  ASSERT_EQ(a.getNumLeafNodes(), b.getNumLeafNodes());
  auto ib = b.begin_leafs();
  std::size_t differing = 0;
  for (auto ia = a.begin_leafs(), end = a.end_leafs(); ia != end; ++ia, ++ib) {
    differing += ia.getKey() != ib.getKey() || ia.getDepth() != ib.getDepth() ||
                 ia->getLogOdds() != ib->getLogOdds();
  }
  EXPECT_EQ(differing, 0U);
}

/// A fresh fusion of `robots` at their final maps and poses.
std::unique_ptr<GlobalFusion> from_scratch(const std::vector<std::pair<std::string, std::pair<Tree, Eigen::Matrix4d>>>& robots,
                                           double res) {
  auto g = std::make_unique<GlobalFusion>(res);
  for (const auto& [id, m] : robots) EXPECT_TRUE(g->set(id, m.first, m.second).ok) << id;
  return g;
}

class GlobalFusionTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() { world_ = test::load("geb079.bt").release(); }
  static void TearDownTestSuite() { delete world_; }
  static octomap::OcTree* world_;
};
octomap::OcTree* GlobalFusionTest::world_ = nullptr;

TEST_F(GlobalFusionTest, UpdatesPoseChangesAndRemovalsEqualAFusionFromScratch) {
  const double res = world_->getResolution();
  Robot r1 = cut(*world_, "r1", -20, -2, 0.0);  // the reference: identity frame
  r1.T_robot_world = Eigen::Isometry3d::Identity();
  r1.map = Tree(crop_and_transform(*world_, Eigen::AlignedBox3d(Eigen::Vector3d(-20, -20, -5), Eigen::Vector3d(-2, 20, 5)),
                                   r1.T_robot_world));
  const Robot r2 = cut(*world_, "r2", -8, 6, 1.1);
  const Robot r3 = cut(*world_, "r3", 2, 20, -2.3);
  const Robot r2_grown = cut(*world_, "r2", -8, 12, 1.1);  // the same frame, a grown map
  const Robot r2_shrunk = cut(*world_, "r2", -5, 9, 1.1);  // lost and gained parts

  GlobalFusion g(res);
  ASSERT_TRUE(g.set("r1", r1.map, T_global(r1)).ok);
  ASSERT_TRUE(g.set("r2", r2.map, T_global(r2)).ok);
  ASSERT_TRUE(g.set("r3", r3.map, T_global(r3)).ok);
  const GlobalFuseResult grown = g.set("r2", r2_grown.map, T_global(r2));
  ASSERT_TRUE(grown.ok);
  EXPECT_TRUE(grown.incremental);  // same pose, same grid: only the difference was fused
  EXPECT_LT(grown.cubes, r2_grown.map->getNumLeafNodes() / 2);
  // A refined pose of r3 (a few cm, a fraction of a degree): its contribution moves.
  Eigen::Matrix4d T3 = T_global(r3);
  T3.topLeftCorner<3, 3>() = T3.topLeftCorner<3, 3>() * Eigen::AngleAxisd(0.004, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  T3(0, 3) += 0.03;
  const GlobalFuseResult moved = g.set("r3", r3.map, T3);
  ASSERT_TRUE(moved.ok);
  EXPECT_FALSE(moved.incremental);
  g.encode();  // prunes the sums in between: later updates must not depend on it
  g.remove("r1");
  ASSERT_TRUE(g.set("r2", r2_shrunk.map, T_global(r2)).ok);
  ASSERT_TRUE(g.set("r1", r1.map, T_global(r1)).ok);
  g.remove("r3");
  ASSERT_TRUE(g.set("r3", r3.map, T3).ok);
  EXPECT_EQ(g.robots(), (std::vector<std::string>{"r1", "r2", "r3"}));

  // From scratch, in another order.
  const auto fresh = from_scratch({{"r3", {r3.map, T3}}, {"r1", {r1.map, T_global(r1)}}, {"r2", {r2_shrunk.map, T_global(r2)}}}, res);
  const auto a = g.tree();
  const auto b = fresh->tree();
  EXPECT_GT(a->getNumLeafNodes(), 50'000U);
  expect_same_voxels(*a, *b);
  EXPECT_TRUE(g.encode().bt == fresh->encode().bt) << "the encoded global maps differ";

  // Everything out: nothing left, not even free space.
  for (const char* id : {"r1", "r2", "r3"}) g.remove(id);
  EXPECT_TRUE(g.empty());
  EXPECT_EQ(g.tree()->size(), 0U);
  EXPECT_EQ(g.encode().nodes, 0U);
}

/// An occupied cube of 64^3 voxels at `corner` (aligned to 64 voxels): one leaf once pruned, so
/// fusing it adds blocks larger than the encoder's cached blocks.
Tree aligned_cube(double res, const octomap::point3d& corner) {
  auto t = std::make_shared<octomap::OcTree>(res);
  const octomap::OcTreeKey k0 = t->coordToKey(corner);
  for (unsigned x = 0; x < 64; ++x) {
    for (unsigned y = 0; y < 64; ++y) {
      for (unsigned z = 0; z < 64; ++z) {
        t->setNodeValue(octomap::OcTreeKey(static_cast<octomap::key_type>((k0[0] & ~63U) + x),
                                           static_cast<octomap::key_type>((k0[1] & ~63U) + y),
                                           static_cast<octomap::key_type>((k0[2] & ~63U) + z)),
                        2.0f, true);
      }
    }
  }
  t->prune();
  return t;
}

using FleetState = std::vector<std::pair<std::string, std::pair<Tree, Eigen::Matrix4d>>>;

/// A fleet's maps over time: a second robot, a grown map (fused by difference), a moved pose, a
/// large aligned block in and out, a robot out and a map shrunk, a whole building in.
std::vector<FleetState> change_steps(const octomap::OcTree& world) {
  const double res = world.getResolution();
  const Robot r2 = cut(world, "r2", -8, 6, 1.1);
  const Robot r2_grown = cut(world, "r2", -8, 12, 1.1);
  const Robot r2_shrunk = cut(world, "r2", -5, 9, 1.1);
  const Robot r3 = cut(world, "r3", 2, 20, -2.3);
  const Tree cube = aligned_cube(res, octomap::point3d(1.0f, 1.0f, 0.0f));
  EXPECT_EQ(cube->getNumLeafNodes(), 1U);
  Eigen::Matrix4d T3 = T_global(r3);
  T3(0, 3) += 0.05;
  return {
      {{"r2", {r2.map, T_global(r2)}}},
      {{"r2", {r2.map, T_global(r2)}}, {"r3", {r3.map, T_global(r3)}}},
      {{"r2", {r2_grown.map, T_global(r2)}}, {"r3", {r3.map, T_global(r3)}}},           // by difference
      {{"r2", {r2_grown.map, T_global(r2)}}, {"r3", {r3.map, T3}}},                      // moved
      {{"r2", {r2_grown.map, T_global(r2)}}, {"r3", {r3.map, T3}}, {"c", {cube, Eigen::Matrix4d::Identity()}}},
      {{"r2", {r2_shrunk.map, T_global(r2)}}, {"c", {cube, Eigen::Matrix4d::Identity()}}},  // r3 out, r2 shrinks
      {{"r2", {r2_shrunk.map, T_global(r2)}}},                                          // the big block out
      {{"w", {Tree(new octomap::OcTree(world)), Eigen::Matrix4d::Identity()}}, {"r2", {r2_shrunk.map, T_global(r2)}}},
  };
}

/// Brings `g` from the robots in `in` to `state` (sets every map, removes robots not in it).
void apply_state(GlobalFusion& g, const FleetState& state, std::set<std::string>& in) {
  std::set<std::string> now;
  for (const auto& [id, m] : state) {
    EXPECT_TRUE(g.set(id, m.first, m.second).ok) << id;
    now.insert(id);
  }
  for (const auto& id : in) {
    if (now.count(id) == 0) g.remove(id);
  }
  in = now;
}

TEST_F(GlobalFusionTest, EncodingAfterEveryChangeEqualsAFreshEncoding) {
  // encode() copies the bytes of unchanged blocks from the previous encoding: after each step
  // the bytes must be exactly those of a fresh fusion of the same maps.
  const double res = world_->getResolution();
  const std::vector<FleetState> steps = change_steps(*world_);
  GlobalFusion g(res);
  std::set<std::string> in;
  for (std::size_t k = 0; k < steps.size(); ++k) {
    apply_state(g, steps[k], in);
    const auto encoded = g.encode();
    const auto fresh = from_scratch(steps[k], res)->encode();
    EXPECT_EQ(encoded.nodes, fresh.nodes) << "step " << k;
    EXPECT_TRUE(encoded.bt == fresh.bt) << "step " << k << ": the encoded global maps differ";
    EXPECT_TRUE(g.encode().bt == fresh.bt) << "step " << k << ": encoding twice changed the bytes";
  }
}

/// Two trees node for node: same size, same structure, same log-odds (inner nodes too).
void expect_same_nodes(const octomap::OcTree& a, const octomap::OcTree& b, const std::string& what) {
  ASSERT_EQ(a.size(), b.size()) << what;
  auto ib = b.begin_tree();
  std::size_t differing = 0;
  for (auto ia = a.begin_tree(), end = a.end_tree(); ia != end; ++ia, ++ib) {
    differing += ia.getKey() != ib.getKey() || ia.getDepth() != ib.getDepth() || ia.isLeaf() != ib.isLeaf() ||
                 ia->getLogOdds() != ib->getLogOdds();
  }
  EXPECT_EQ(differing, 0U) << what;
}

TEST_F(GlobalFusionTest, PatchingThePreviousMapWithTheChangedBlocksGivesTheNewMap) {
  // A receiver holding the tree decoded from one encoding, patched with the next encoding's
  // changed blocks, holds node for node the tree decoded from that next encoding.
  const double res = world_->getResolution();
  std::vector<FleetState> steps = change_steps(*world_);
  steps.push_back({});  // everyone out: an empty map
  steps.push_back(steps[2]);  // and back
  GlobalFusion g(res);
  std::set<std::string> in;
  std::unique_ptr<octomap::OcTree> held;
  // Grown, the cube in, the cube out, everyone out: a part of the map changed. The others
  // (a robot in, a pose moved, a building in) rewrite more than half the map: sent whole.
  const std::set<std::size_t> partial{2, 4, 6, 8};
  for (std::size_t k = 0; k < steps.size(); ++k) {
    const std::string what = "step " + std::to_string(k);
    apply_state(g, steps[k], in);
    const GlobalFusion::Encoded e = g.encode();
    DecodeResult decoded = decode_map(e.bt, Encoding::kOctomapBt, DecodeLimits{});
    ASSERT_TRUE(decoded.ok()) << what << ": " << decoded.reason;
    EXPECT_EQ(e.patches.has_value(), partial.count(k) == 1) << what;
    if (held && e.patches) {
      EXPECT_EQ(check_block_patches(*e.patches, DecodeLimits{}.max_nodes), "") << what;
      std::size_t bytes = 0;
      for (const BlockPatch& p : *e.patches) bytes += p.records.size();
      EXPECT_LE(bytes, e.body.size() / 2) << what;
      apply_block_patches(*held, *e.patches);
      expect_same_nodes(*held, *decoded.tree, what);
      EXPECT_TRUE(encode_map(*held, Encoding::kOctomapBt) == e.bt) << what;
    }
    held = std::move(decoded.tree);
    const GlobalFusion::Encoded again = g.encode();
    EXPECT_TRUE(again.patches.has_value() && again.patches->empty()) << what << ": nothing changed, nothing to patch";
  }
}

TEST(BlockPatches, MalformedPatchesAreRejectedWithAReason) {
  BlockPatch ok{patch_block_of(octomap::OcTreeKey(32768, 32768, 32768)), BlockState::kMixed, {0x02, 0x00}};
  EXPECT_EQ(check_block_patches({ok}, 100), "");
  auto rejects = [](const std::vector<BlockPatch>& patches, const std::string& needle) {
    const std::string reason = check_block_patches(patches, 100);
    EXPECT_NE(reason.find(needle), std::string::npos) << "'" << reason << "' lacks '" << needle << "'";
  };
  BlockPatch p = ok;
  p.block = std::uint64_t{1} << 11;
  rejects({p}, "outside the key space");
  rejects({ok, ok}, "patched twice");
  p = ok;
  p.state = static_cast<BlockState>(7);
  rejects({p}, "unknown block state");
  p = ok;
  p.state = BlockState::kFree;
  rejects({p}, "uniform block with records");
  p = ok;
  p.records = {0x00, 0x00};
  rejects({p}, "without children");
  p.records = {0x02};
  rejects({p}, "mid-node");
  p.records = {0x02, 0x00, 0x00};
  rejects({p}, "bytes after");
  p.records = {0x03, 0x00, 0x03, 0x00, 0x03, 0x00, 0x03, 0x00, 0x03, 0x00, 0x02, 0x00};  // 6 levels below a block
  rejects({p}, "deeper than");
  p.records = {0xFF, 0xFF};  // 8 inner children announced, none follows
  rejects({p}, "before a node");
  p.records = {};
  rejects({p}, "before a node");
  std::vector<BlockPatch> many;
  for (std::uint64_t b = 0; b < 200; ++b) many.push_back(BlockPatch{b, BlockState::kFree, {}});
  rejects(many, "more than 100 nodes");
}

TEST_F(GlobalFusionTest, RandomPatchesAreRejectedOrLeaveAWellFormedTree) {
  // Hostile or garbled patches: check_block_patches() must reject every one that apply could not
  // take; whatever it accepts leaves a tree that encodes and decodes to the same tree.
  const Robot r2 = cut(*world_, "r2", -8, 6, 1.1);
  octomap::OcTree tree(*r2.map);
  tree.toMaxLikelihood();
  tree.prune();
  std::vector<std::uint64_t> blocks;  // blocks of the map, and a few outside it
  for (auto it = tree.begin_leafs(), end = tree.end_leafs(); it != end && blocks.size() < 64; ++it) {
    blocks.push_back(patch_block_of(it.getKey()));
  }
  blocks.push_back(0);
  blocks.push_back(patch_block_of(octomap::OcTreeKey(65535, 65535, 65535)));
  std::mt19937 rng(7);
  std::size_t accepted = 0;
  for (int round = 0; round < 2000; ++round) {
    std::vector<BlockPatch> patches(1 + rng() % 6);
    for (BlockPatch& p : patches) {
      p.block = blocks[rng() % blocks.size()];
      p.state = static_cast<BlockState>(rng() % 5);
      const std::size_t n = rng() % 3 == 0 ? 0 : 2 * (rng() % 12) + rng() % 2;
      for (std::size_t i = 0; i < n; ++i) {  // mostly leaves, some inner children
        std::uint8_t b = 0;
        for (int c = 0; c < 4; ++c) b = static_cast<std::uint8_t>(b | (rng() % 7 == 0 ? 3U : rng() % 3) << (2 * c));
        p.records.push_back(b);
      }
    }
    if (!check_block_patches(patches, 1'000'000).empty()) continue;
    ++accepted;
    apply_block_patches(tree, patches);
    const auto bytes = encode_map(tree, Encoding::kOctomapBt);
    const DecodeResult again = decode_map(bytes, Encoding::kOctomapBt, DecodeLimits{});
    ASSERT_TRUE(again.ok()) << "round " << round << ": " << again.reason;
    ASSERT_EQ(again.tree->size(), tree.size()) << "round " << round;
    ASSERT_TRUE(encode_map(*again.tree, Encoding::kOctomapBt) == bytes) << "round " << round;
  }
  EXPECT_GT(accepted, 30U) << "the generator must also make valid patches";
}

/// `tree` as a robot sends it: encoded as `.bt`, then decoded (tree and binary body).
std::pair<Tree, std::shared_ptr<const std::vector<std::uint8_t>>> sent(const octomap::OcTree& tree) {
  DecodeResult d = decode_map(encode_map(tree, Encoding::kOctomapBt), Encoding::kOctomapBt, DecodeLimits{});
  EXPECT_TRUE(d.ok()) << d.reason;
  EXPECT_TRUE(d.binary_body != nullptr);
  return {Tree(std::move(d.tree)), d.binary_body};
}

/// `tree` as the server receives it: the `.bt` payload checked, its tree not built.
std::shared_ptr<const HeldMap> checked(const octomap::OcTree& tree) {
  const std::vector<std::uint8_t> bytes = encode_map(tree, Encoding::kOctomapBt);
  CheckedMap c = check_map(bytes.data(), bytes.size(), Encoding::kOctomapBt, DecodeLimits{});
  EXPECT_TRUE(c.ok() && c.map) << c.reason;
  EXPECT_FALSE(c.map->has_tree());
  return c.map;
}

TEST_F(GlobalFusionTest, DifferencesReadOffTheBinaryBodiesEqualTheTreeWalk) {
  // The same sequence of received maps of one robot (grown, shrunk, edited inside, back to the
  // first), fused once with the payloads' binary bodies and once from the trees alone: the
  // clamped global maps must agree voxel for voxel and byte for byte after every update.
  const double res = world_->getResolution();
  const Robot r2 = cut(*world_, "r2", -8, 6, 1.1);
  const Robot r3 = cut(*world_, "r3", 2, 20, -2.3);
  const Robot grown = cut(*world_, "r2", -8, 12, 1.1);
  const Robot shrunk = cut(*world_, "r2", -5, 9, 1.1);
  auto edited = std::make_unique<octomap::OcTree>(*shrunk.map);
  double lo[3], hi[3];
  edited->getMetricMin(lo[0], lo[1], lo[2]);
  edited->getMetricMax(hi[0], hi[1], hi[2]);
  const double cx = 0.5 * (lo[0] + hi[0]), cy = 0.5 * (lo[1] + hi[1]), cz = 0.5 * (lo[2] + hi[2]);
  for (double x = cx; x < cx + 1.3; x += res)  // a block made occupied: prunes into large leaves
    for (double y = cy; y < cy + 1.3; y += res)
      for (double z = cz; z < cz + 0.7; z += res) edited->updateNode(octomap::point3d(x, y, z), true);
  for (double x = cx - 2.0; x < cx - 1.0; x += res)  // a block made free, known where it was not
    for (double y = cy - 2.0; y < cy - 1.0; y += res)
      for (double z = lo[2]; z < hi[2]; z += res) edited->setNodeValue(octomap::point3d(x, y, z), -2.0f);
  edited->prune();
  const std::vector<std::pair<const octomap::OcTree*, const char*>> updates{
      {r2.map.get(), "first"},
      {grown.map.get(), "grown"},
      {shrunk.map.get(), "shrunk"},
      {edited.get(), "edited"},
      {r2.map.get(), "the first again"},
  };
  const auto [r3_map, r3_body] = sent(*r3.map);
  GlobalFusion with_bodies(res), trees_only(res), checked_only(res);
  ASSERT_TRUE(with_bodies.set("r3", r3_map, T_global(r3), r3_body).ok);
  ASSERT_TRUE(trees_only.set("r3", r3_map, T_global(r3)).ok);
  ASSERT_TRUE(checked_only.set("r3", checked(*r3.map), T_global(r3)).ok);
  std::vector<Tree> held;  // GlobalFusion holds only the latest map of a robot
  for (std::size_t k = 0; k < updates.size(); ++k) {
    const auto [map, body] = sent(*updates[k].first);
    held.push_back(map);
    const GlobalFuseResult a = with_bodies.set("r2", map, T_global(r2), body);
    const GlobalFuseResult b = trees_only.set("r2", map, T_global(r2));
    // As the server receives it: a checked body whose tree is built only if fusion needs it.
    const std::shared_ptr<const HeldMap> lazy = checked(*updates[k].first);
    const GlobalFuseResult c = checked_only.set("r2", lazy, T_global(r2));
    ASSERT_TRUE(a.ok && b.ok && c.ok) << updates[k].second;
    EXPECT_FALSE(lazy->has_tree()) << updates[k].second << ": fused off its bytes, whole or by difference";
    EXPECT_EQ(c.cubes, b.cubes) << updates[k].second;
    EXPECT_TRUE(checked_only.encode().bt == trees_only.encode().bt) << updates[k].second;
    EXPECT_EQ(a.incremental, k > 0) << updates[k].second;
    EXPECT_EQ(a.from_bodies, k > 0) << updates[k].second;
    EXPECT_FALSE(b.from_bodies);
    EXPECT_EQ(a.cubes, b.cubes) << updates[k].second;
    EXPECT_EQ(a.work, b.work) << updates[k].second;  // what FuseConfig::max_work is checked against
    expect_same_voxels(*with_bodies.tree(), *trees_only.tree());
    EXPECT_TRUE(with_bodies.encode().bt == trees_only.encode().bt) << updates[k].second;
  }
  EXPECT_TRUE(with_bodies.map_of("r2")->binary_body() != nullptr);
  EXPECT_TRUE(trees_only.map_of("r2")->binary_body() == nullptr);
  // Moved (fused whole again: taken out at the old pose, put in at the new one), then another
  // robot taken out: off the bytes, with no tree built, the sums of a fusion of the trees.
  Eigen::Matrix4d moved = T_global(r2);
  moved(0, 3) += 0.37;
  moved(1, 3) -= 0.21;
  const GlobalFuseResult m = checked_only.set("r2", checked_only.map_of("r2"), moved);  // the first map again
  ASSERT_TRUE(m.ok);
  EXPECT_FALSE(m.incremental);
  GlobalFusion scratch(res);
  ASSERT_TRUE(scratch.set("r3", r3.map, T_global(r3)).ok);
  const GlobalFuseResult s2 = scratch.set("r2", r2.map, moved);
  ASSERT_TRUE(s2.ok);
  EXPECT_EQ(m.work, s2.work);
  EXPECT_TRUE(checked_only.encode().bt == scratch.encode().bt) << "moved";
  checked_only.remove("r3");
  scratch.remove("r3");
  EXPECT_TRUE(checked_only.encode().bt == scratch.encode().bt) << "r3 taken out";
  expect_same_voxels(*checked_only.tree(), *scratch.tree());
  EXPECT_FALSE(checked_only.map_of("r2")->has_tree());
  // A body that is not the complete tree (here cut short) is not trusted: the trees are walked.
  const auto [map, body] = sent(*grown.map);
  const auto cut_short = std::make_shared<const std::vector<std::uint8_t>>(body->begin(), body->begin() + body->size() / 2);
  const GlobalFuseResult a = with_bodies.set("r2", map, T_global(r2), cut_short);
  const GlobalFuseResult b = trees_only.set("r2", map, T_global(r2));
  ASSERT_TRUE(a.ok && b.ok);
  EXPECT_TRUE(a.incremental);
  EXPECT_FALSE(a.from_bodies);
  expect_same_voxels(*with_bodies.tree(), *trees_only.tree());
}

TEST_F(GlobalFusionTest, ASubVoxelPoseChangeOfAGrownMapKeepsTheFusedPoseALargerOneMovesTheMap) {
  // What the server asks when a refinement has moved a robot a little and its map has grown:
  // fuse the difference at the fused pose if no leaf, old or new, moves by half a voxel.
  const double res = world_->getResolution();
  const double half_voxel = 0.5 * res;
  const Robot r2 = cut(*world_, "r2", -8, 6, 1.1);
  const Robot grown = cut(*world_, "r2", -8, 12, 1.1);
  const Eigen::Matrix4d T = T_global(r2);
  const auto first = checked(*r2.map);
  const auto next = checked(*grown.map);
  const auto fresh_encoding = [&](const Eigen::Matrix4d& pose) {
    GlobalFusion scratch(res);
    EXPECT_TRUE(scratch.set("r2", grown.map, pose).ok);
    return scratch.encode().bt;
  };
  const auto contains = [](const Eigen::AlignedBox3d& outer, const Eigen::AlignedBox3d& inner) {
    return (outer.min().array() <= inner.min().array() + 1e-9).all() &&
           (outer.max().array() >= inner.max().array() - 1e-9).all();
  };
  // The poses: a 1 cm shift (kept); a turn about the robot's origin that moves no fused leaf by
  // half a voxel but moves the grown part's farthest leaves by more (moved); a 30 cm shift.
  GlobalFusion probe(res);
  ASSERT_TRUE(probe.set("r2", first, T).ok);
  const Eigen::AlignedBox3d fused_box = *probe.extent_of("r2");
  EXPECT_TRUE(contains(fused_box, leaf_bounds(*r2.map)));
  const auto turned = [&](double angle) {
    Eigen::Matrix4d t = T;
    t.topLeftCorner<3, 3>() = T.topLeftCorner<3, 3>() * Eigen::AngleAxisd(angle, Eigen::Vector3d::UnitZ()).toRotationMatrix();
    return t;
  };
  const double reach_fused = max_displacement(T, turned(1e-4), fused_box) / 1e-4;
  const double reach_grown = max_displacement(T, turned(1e-4), leaf_bounds(*grown.map)) / 1e-4;
  ASSERT_GT(reach_grown, 1.1 * reach_fused) << "the grown part must reach farther from the origin";
  const double angle = 2.0 * half_voxel / (reach_fused + reach_grown);
  ASSERT_LT(max_displacement(T, turned(angle), fused_box), half_voxel);
  ASSERT_GT(max_displacement(T, turned(angle), leaf_bounds(*grown.map)), half_voxel);
  Eigen::Matrix4d shifted = T;
  shifted(0, 3) += 0.01;
  Eigen::Matrix4d far = T;
  far(1, 3) += 0.3;

  struct Case {
    const char* name;
    Eigen::Matrix4d pose;
    bool kept;
  };
  for (const Case& c : {Case{"1 cm", shifted, true}, Case{"turn", turned(angle), false}, Case{"30 cm", far, false}}) {
    SCOPED_TRACE(c.name);
    GlobalFusion g(res);
    ASSERT_TRUE(g.set("r2", first, T).ok);
    const GlobalFuseResult r = g.set("r2", next, c.pose, half_voxel);
    ASSERT_TRUE(r.ok);
    EXPECT_EQ(r.kept_pose, c.kept);
    EXPECT_EQ(r.incremental, c.kept);
    EXPECT_TRUE(*g.pose_of("r2") == (c.kept ? T : c.pose));
    EXPECT_TRUE(contains(*g.extent_of("r2"), leaf_bounds(*grown.map)));
    EXPECT_TRUE(g.encode().bt == fresh_encoding(c.kept ? T : c.pose)) << "differs from a fusion at the pose it reports";
    EXPECT_FALSE(next->has_tree());
  }
  // Without keep_pose_within, any new pose fuses the map whole at that pose.
  GlobalFusion exact(res);
  ASSERT_TRUE(exact.set("r2", first, T).ok);
  const GlobalFuseResult r = exact.set("r2", next, shifted);
  EXPECT_FALSE(r.kept_pose);
  EXPECT_TRUE(*exact.pose_of("r2") == shifted);
  EXPECT_TRUE(exact.encode().bt == fresh_encoding(shifted));
}

TEST_F(GlobalFusionTest, AMoveInStepsKeepsEveryLeafOnceAndEndsAsAFusionAtTheNewPose) {
  // What the server does when the pose graph moves a fused robot whose map did not change: the
  // move goes in steps of a few leaves, one a build. Whatever happens halfway (the last steps,
  // another pose, a grown map, the robot taken out), the result must be byte for byte the fresh
  // fusion of what was asked last: a leaf counted twice or not at all would show.
  const double res = world_->getResolution();
  const Robot r1 = cut(*world_, "r1", -20, -2, 0.0);
  const Robot r2 = cut(*world_, "r2", -8, 6, 1.1);
  const Robot grown = cut(*world_, "r2", -8, 12, 1.1);
  const auto m1 = checked(*r1.map);
  const auto m2 = checked(*r2.map);
  const auto m2_grown = checked(*grown.map);
  const Eigen::Matrix4d T1 = T_global(r1), T2 = T_global(r2);
  const Eigen::Matrix4d moved = T2 * make_transform(0.3, -0.2, 0.05, 0.02, 0.0, 0.1).matrix();
  const Eigen::Matrix4d again = T2 * make_transform(-0.1, 0.1, 0.0, 0.0, 0.01, -0.05).matrix();
  const auto fresh = [&](std::shared_ptr<const HeldMap> second, const Eigen::Matrix4d& pose) {
    GlobalFusion scratch(res);
    EXPECT_TRUE(scratch.set("r1", m1, T1).ok);
    if (second) {
      EXPECT_TRUE(scratch.set("r2", second, pose).ok);
    }
    return scratch.encode().bt;
  };
  const std::size_t step = r2.map->getNumLeafNodes() / 4;
  ASSERT_GT(step, 1000U);
  const auto started = [&](GlobalFusion& g) {
    EXPECT_TRUE(g.set("r1", m1, T1).ok);
    EXPECT_TRUE(g.set("r2", m2, T2).ok);
    const GlobalFuseResult r = g.set("r2", m2, moved, 0.0, step);
    EXPECT_TRUE(r.ok && r.moving);
    EXPECT_FALSE(r.incremental);
    EXPECT_LE(r.cubes, 2 * step) << "a step takes out and puts in at most its leaves";
  };

  GlobalFusion g(res);
  started(g);
  const auto before = fresh(m2, T2), after = fresh(m2, moved);
  int calls = 1;
  while (g.moving("r2")) {
    EXPECT_FALSE(g.holds("r2", m2.get(), moved));
    EXPECT_TRUE(*g.pose_of("r2") == moved);
    const auto halfway = g.encode().bt;
    EXPECT_TRUE(halfway != before && halfway != after) << "after " << calls << " steps";
    const GlobalFuseResult r = g.set("r2", m2, moved, 0.0, step);
    ASSERT_TRUE(r.ok);
    EXPECT_EQ(r.moving, g.moving("r2"));
    ASSERT_LT(++calls, 50);
  }
  EXPECT_GE(calls, 4);
  EXPECT_LE(calls, 8);
  EXPECT_TRUE(g.holds("r2", m2.get(), moved));
  EXPECT_TRUE(g.encode().bt == after) << "the last step does not end at a fusion at the new pose";
  EXPECT_FALSE(m2->has_tree()) << "a move in steps reads the map's bytes";

  // Halfway: another pose (the move ends at once, then the map moves whole), new maps (each by
  // its difference, at once, and the move goes on with it), the robot taken out, a move of one
  // whole step.
  GlobalFusion other_pose(res);
  started(other_pose);
  ASSERT_TRUE(other_pose.set("r2", m2, again).ok);
  EXPECT_FALSE(other_pose.moving("r2"));
  EXPECT_TRUE(other_pose.encode().bt == fresh(m2, again));
  // New maps while moving: grown; then every known leaf occupied and the tree pruned, and at
  // once (no step in between) the same leaves free: larger leaves than the moving map's, so some
  // lie across the boundary its steps left and are cut there; then the first map again (the
  // grown part taken out). Each goes in without a step.
  octomap::OcTree coarse_tree(*grown.map);
  for (auto it = coarse_tree.begin_leafs(), end = coarse_tree.end_leafs(); it != end; ++it) {
    it->setLogOdds(coarse_tree.getClampingThresMaxLog());
  }
  coarse_tree.prune();
  ASSERT_LT(coarse_tree.getNumLeafNodes(), grown.map->getNumLeafNodes());
  octomap::OcTree coarse_free_tree(coarse_tree);
  for (auto it = coarse_free_tree.begin_leafs(), end = coarse_free_tree.end_leafs(); it != end; ++it) {
    it->setLogOdds(coarse_free_tree.getClampingThresMinLog());
  }
  const auto m2_coarse = checked(coarse_tree);
  const auto m2_coarse_free = checked(coarse_free_tree);
  const auto new_maps = [&](GlobalFusion& fusion) {
    started(fusion);
    for (const auto& [next, step_after] : {std::pair{m2_grown, true}, std::pair{m2_coarse, false},
                                           std::pair{m2_coarse_free, true}, std::pair{m2, true}}) {
      const GlobalFuseResult r = fusion.set("r2", next, moved, 0.0, step);
      ASSERT_TRUE(r.ok);
      EXPECT_TRUE(r.moving && r.incremental && r.from_bodies) << "a new map halfway goes in by its difference";
      EXPECT_TRUE(fusion.map_of("r2") == next);
      if (step_after) {
        ASSERT_TRUE(fusion.set("r2", next, moved, 0.0, step / 4).ok);  // the move's next step, with the new map
      }
      ASSERT_TRUE(fusion.moving("r2"));
    }
  };
  GlobalFusion grew(res);
  new_maps(grew);
  for (int n = 1; grew.moving("r2"); ++n) {
    ASSERT_TRUE(grew.set("r2", m2, moved, 0.0, step).ok);
    ASSERT_LT(n, 50);
  }
  EXPECT_TRUE(grew.encode().bt == after) << "new maps halfway: not the fresh fusion at the end";
  GlobalFusion grew_removed(res);
  new_maps(grew_removed);
  grew_removed.remove("r2");
  EXPECT_TRUE(grew_removed.encode().bt == fresh(nullptr, T2)) << "new maps halfway: a leaf counted twice or not at all";
  GlobalFusion grew_other_pose(res);
  new_maps(grew_other_pose);
  ASSERT_TRUE(grew_other_pose.set("r2", m2_grown, again, 0.0, step).ok);  // ends the move, then moves whole
  EXPECT_TRUE(grew_other_pose.encode().bt == fresh(m2_grown, again));
  GlobalFusion removed(res);
  started(removed);
  removed.remove("r2");
  EXPECT_TRUE(removed.encode().bt == fresh(nullptr, T2));
  // A grown map whose pose moved too far to keep (the server's keep_pose_within): its difference
  // at the fused pose first, in the same call the move's first step, then the steps.
  GlobalFusion both(res);
  ASSERT_TRUE(both.set("r1", m1, T1).ok);
  ASSERT_TRUE(both.set("r2", m2, T2).ok);
  const GlobalFuseResult b = both.set("r2", m2_grown, moved, 0.5 * res, step);
  EXPECT_TRUE(b.ok && b.incremental && b.kept_pose && b.moving);
  for (int n = 1; both.moving("r2"); ++n) {
    ASSERT_TRUE(both.set("r2", m2_grown, moved, 0.5 * res, step).ok);
    ASSERT_LT(n, 50);
  }
  EXPECT_TRUE(both.encode().bt == fresh(m2_grown, moved));
  GlobalFusion one_step(res);
  ASSERT_TRUE(one_step.set("r1", m1, T1).ok);
  ASSERT_TRUE(one_step.set("r2", m2, T2).ok);
  const GlobalFuseResult whole = one_step.set("r2", m2, moved, 0.0, 100 * step);
  EXPECT_TRUE(whole.ok && !whole.moving);
  EXPECT_TRUE(one_step.encode().bt == after);
}

TEST_F(GlobalFusionTest, OneThreadOrSeveralGiveTheSameBytes) {
  // set() shares a map's cubes out over the global map's blocks, written on several threads.
  // After every step of the same changes (received as checked payloads, so fused off their
  // bytes: whole maps in runs, grown ones by difference), one thread's global map and four
  // threads' must be the same bytes with the same changed blocks.
  const double res = world_->getResolution();
  const std::vector<FleetState> steps = change_steps(*world_);
  GlobalFusion one(res), four(res);
  one.set_threads(1);
  four.set_threads(4);
  ASSERT_EQ(one.threads(), 1U);
  ASSERT_EQ(four.threads(), 4U);
  std::set<std::string> in;
  for (std::size_t k = 0; k < steps.size(); ++k) {
    std::set<std::string> now;
    for (const auto& [id, m] : steps[k]) {
      const std::shared_ptr<const HeldMap> held = checked(*m.first);
      const GlobalFuseResult a = one.set(id, held, m.second);
      const GlobalFuseResult b = four.set(id, held, m.second);
      EXPECT_TRUE(a.ok && b.ok) << "step " << k << " " << id;
      EXPECT_EQ(a.cubes, b.cubes) << "step " << k << " " << id;
      now.insert(id);
    }
    for (const auto& id : in) {
      if (now.count(id) == 0) {
        one.remove(id);
        four.remove(id);
      }
    }
    in = now;
    const auto a = one.encode();
    const auto b = four.encode();
    EXPECT_GT(a.nodes, 0U) << "step " << k;
    EXPECT_EQ(a.nodes, b.nodes) << "step " << k;
    EXPECT_TRUE(a.bt == b.bt) << "step " << k << ": one thread's global map and four threads' differ";
    ASSERT_EQ(a.patches.has_value(), b.patches.has_value()) << "step " << k;
    if (a.patches) {
      EXPECT_EQ(a.patches->size(), b.patches->size()) << "step " << k;
    }
  }
}

TEST_F(GlobalFusionTest, EncodedMapIsTheMaximumLikelihoodOfTheClampedSums) {
  const double res = world_->getResolution();
  const Robot r2 = cut(*world_, "r2", -8, 6, 1.1);
  const Robot r3 = cut(*world_, "r3", 2, 20, -2.3);
  GlobalFusion g(res);
  ASSERT_TRUE(g.set("r2", r2.map, T_global(r2)).ok);
  ASSERT_TRUE(g.set("r3", r3.map, T_global(r3)).ok);
  const GlobalFusion::Encoded e = g.encode();
  const DecodeResult d = decode_map(e.bt, Encoding::kOctomapBt, DecodeLimits{});
  ASSERT_TRUE(d.ok()) << d.reason;
  EXPECT_EQ(d.num_nodes, e.nodes);
  // The body is what octomap_msgs carries: the same tree.
  const DecodeResult body = decode_tree_body("OcTree", res, true, e.body, DecodeLimits{});
  ASSERT_TRUE(body.ok()) << body.reason;
  auto expected = g.tree();
  expected->toMaxLikelihood();
  expected->prune();
  expect_same_voxels(*d.tree, *expected);
  expect_same_voxels(*body.tree, *expected);
}

TEST_F(GlobalFusionTest, DisjointMapsMatchFuseIntoAndOverlapClampsOnlyTheSum) {
  const double res = world_->getResolution();
  const Robot r1 = cut(*world_, "r1", -20, -6, 0.4);
  const Robot r3 = cut(*world_, "r3", 6, 20, -2.3);
  GlobalFusion g(res);
  ASSERT_TRUE(g.set("r1", r1.map, T_global(r1)).ok);
  ASSERT_TRUE(g.set("r3", r3.map, T_global(r3)).ok);
  // No voxel gets evidence from both: the same as fuse_into, up to the 1/4096 quantum.
  octomap::OcTree reference(res);
  FuseConfig config;
  ASSERT_TRUE(fuse_into(reference, *r1.map, T_global(r1), config).ok);
  ASSERT_TRUE(fuse_into(reference, *r3.map, T_global(r3), config).ok);
  const auto mine = g.tree();
  std::size_t checked = 0;
  for (auto it = reference.begin_leafs(16), end = reference.end_leafs(); it != end; ++it) {
    const octomap::OcTreeNode* n = mine->search(it.getKey());
    ASSERT_NE(n, nullptr);
    ASSERT_NEAR(n->getLogOdds(), it->getLogOdds(), 1.0 / 8192 + 1e-6);
    ++checked;
  }
  EXPECT_GT(checked, 10'000U);
  // Two robots on the same voxel: their evidence is summed, then clamped once.
  GlobalFusion twice(res);
  ASSERT_TRUE(twice.set("a", r1.map, T_global(r1)).ok);
  ASSERT_TRUE(twice.set("b", r1.map, T_global(r1)).ok);
  const auto both = twice.tree();
  const float max = both->getClampingThresMaxLog();
  const float min = both->getClampingThresMinLog();
  for (auto it = both->begin_leafs(), end = both->end_leafs(); it != end; ++it) {
    ASSERT_TRUE(it->getLogOdds() == max || it->getLogOdds() == min);  // 2 x 3.5 and 2 x -2.0
  }
}

TEST_F(GlobalFusionTest, RefusedMapsLeaveTheRobotOutAndTheOthersIntact) {
  const double res = world_->getResolution();
  const Robot r1 = cut(*world_, "r1", -20, -6, 0.4);
  const Robot r3 = cut(*world_, "r3", 6, 20, -2.3);
  GlobalFusion g(res);
  ASSERT_TRUE(g.set("r1", r1.map, T_global(r1)).ok);
  ASSERT_TRUE(g.set("r3", r3.map, T_global(r3)).ok);
  Eigen::Matrix4d scaled = T_global(r3);
  scaled(0, 0) *= 2.0;
  const GlobalFuseResult bad = g.set("r3", r3.map, scaled);
  EXPECT_FALSE(bad.ok);
  EXPECT_FALSE(bad.reason.empty());
  EXPECT_FALSE(g.set("r4", Tree(), Eigen::Matrix4d::Identity()).ok);
  EXPECT_EQ(g.robots(), std::vector<std::string>{"r1"});
  GlobalFusion only_r1(res);
  ASSERT_TRUE(only_r1.set("r1", r1.map, T_global(r1)).ok);
  EXPECT_TRUE(g.encode().bt == only_r1.encode().bt) << "r3 left traces";
  // Too much work for the limit: refused the same way.
  FuseConfig tight;
  tight.max_work = 1000;
  GlobalFusion small(res, tight);
  EXPECT_FALSE(small.set("r1", r1.map, T_global(r1)).ok);
  EXPECT_TRUE(small.empty());
}

TEST_F(GlobalFusionTest, AFullBodyIsPlacedAsItsTreeWithoutBuildingIt) {
  // A `.ot` map is held as its full body (log-odds kept): placed, removed and staged off its
  // bytes, it must give the bytes its tree gives, on its own grid, a coarser and a finer one.
  const Robot r1 = cut(*world_, "r1", -20, -2, 0.0);
  const Robot r2 = cut(*world_, "r2", -8, 6, 1.1);
  auto graded = std::make_shared<octomap::OcTree>(*r2.map);  // log-odds not all at a bound
  std::vector<octomap::OcTreeKey> keys;
  std::size_t i = 0;
  for (auto it = graded->begin_leafs(), end = graded->end_leafs(); it != end; ++it, ++i) {
    if (i % 3 == 0 && it.getDepth() == graded->getTreeDepth()) keys.push_back(it.getKey());
  }
  for (std::size_t k = 0; k < keys.size(); ++k) graded->updateNode(keys[k], k % 2 == 0);
  const auto full = [](const octomap::OcTree& tree) {
    const auto ot = encode_map(tree, Encoding::kOctomapOt);
    const CheckedMap c = check_map(ot.data(), ot.size(), Encoding::kOctomapOt, {});
    EXPECT_TRUE(c.ok() && c.map && c.map->full_body()) << c.reason;
    return c.map;
  };
  const auto t1 = std::make_shared<const HeldMap>(r1.map), t2 = std::make_shared<const HeldMap>(graded);
  const auto f1 = full(*r1.map), f2 = full(*graded);
  for (const double res : {world_->getResolution(), 0.2, world_->getResolution() / 2}) {
    GlobalFusion trees(res), bodies(res), staged(res);
    for (auto* g : {&trees, &bodies, &staged}) g->set_threads(2);
    ASSERT_TRUE(trees.set("r1", t1, T_global(r1)).ok);
    ASSERT_TRUE(trees.set("r2", t2, T_global(r2)).ok);
    ASSERT_TRUE(bodies.set("r1", f1, T_global(r1)).ok);
    const GlobalFuseResult b = bodies.set("r2", f2, T_global(r2));
    ASSERT_TRUE(b.ok);
    EXPECT_GT(b.cubes, 1000U);
    staged.stage(f1);
    ASSERT_TRUE(staged.set("r1", f1, T_global(r1)).ok);
    staged.stage(f2);
    const GlobalFuseResult s = staged.set("r2", f2, T_global(r2));
    ASSERT_TRUE(s.ok);
    EXPECT_EQ(b.work, s.work);
    EXPECT_TRUE(trees.encode().bt == bodies.encode().bt) << "full bodies and trees differ at " << res << " m";
    EXPECT_TRUE(trees.encode().bt == staged.encode().bt) << "staged full bodies differ at " << res << " m";
    trees.remove("r2");
    bodies.remove("r2");
    EXPECT_TRUE(trees.encode().bt == bodies.encode().bt) << "a full body's removal differs at " << res << " m";
  }
  EXPECT_FALSE(f1->has_tree());
  EXPECT_FALSE(f2->has_tree());
}

TEST_F(GlobalFusionTest, AMapOnItsOwnGridIsItsOwnGlobalMap) {
  // A map at the identity pose on a grid of its resolution is added leaf by leaf, not resampled
  // (the anchor robot; the target of `mapmerge merge`). Alone, its global map is its own bytes,
  // whichever way it is held; with a second map it is the same as fused after a resampled one.
  const auto bt = encode_map(*world_, Encoding::kOctomapBt);
  const auto ot = encode_map(*world_, Encoding::kOctomapOt);
  const std::shared_ptr<const HeldMap> held[] = {
      check_map(bt.data(), bt.size(), Encoding::kOctomapBt, {}).map,
      check_map(ot.data(), ot.size(), Encoding::kOctomapOt, {}).map,
      std::make_shared<const HeldMap>(Tree(new octomap::OcTree(*world_)))};
  const Robot r2 = cut(*world_, "r2", -8, 6, 1.1);
  GlobalFusion after_other(world_->getResolution());
  ASSERT_TRUE(after_other.set("r2", r2.map, T_global(r2)).ok);
  ASSERT_TRUE(after_other.set("w", held[0], Eigen::Matrix4d::Identity()).ok);
  const auto both = after_other.encode().bt;
  for (const auto& map : held) {
    ASSERT_TRUE(map);
    GlobalFusion g(world_->getResolution());
    const GlobalFuseResult r = g.set("w", map, Eigen::Matrix4d::Identity());
    ASSERT_TRUE(r.ok);
    EXPECT_EQ(r.voxel_updates + r.block_updates, r.cubes);
    EXPECT_TRUE(g.encode().bt == bt) << "the map alone is not its own bytes";
    ASSERT_TRUE(g.set("r2", r2.map, T_global(r2)).ok);
    EXPECT_TRUE(g.encode().bt == both) << "placed before or after another map: not the same sums";
    g.remove("r2");
    EXPECT_TRUE(g.encode().bt == bt);
  }
}

TEST_F(GlobalFusionTest, AStagedMapIsPlacedAsAnUnstagedOne) {
  // stage() walks a map's octree ahead of its set(). Maps without a body (as `.ot` files are
  // read), one of them finer than the grid (voted per voxel): the global map must be the same
  // bytes as without staging, whether the staged map is the one set next or another.
  const Robot r1 = cut(*world_, "r1", -20, -2, 0.4);
  const Robot r2 = cut(*world_, "r2", -8, 6, 1.1);
  for (const double res : {world_->getResolution(), 0.2}) {
    const auto m1 = std::make_shared<const HeldMap>(r1.map), m2 = std::make_shared<const HeldMap>(r2.map);
    ASSERT_EQ(m1->binary_body(), nullptr);
    GlobalFusion plain(res), staged(res);
    GlobalFuseResult a = plain.set("r1", m1, T_global(r1)), b;
    ASSERT_TRUE(a.ok);
    staged.stage(m2);  // not the map set next: unused
    b = staged.set("r1", m1, T_global(r1));
    ASSERT_TRUE(b.ok);
    EXPECT_EQ(a.work, b.work);
    a = plain.set("r2", m2, T_global(r2));
    staged.stage(m2);
    b = staged.set("r2", m2, T_global(r2));
    ASSERT_TRUE(a.ok && b.ok);
    EXPECT_EQ(a.work, b.work) << res;
    EXPECT_EQ(a.cubes, b.cubes) << res;
    EXPECT_GT(b.cubes, 1000U);
    EXPECT_TRUE(plain.encode().bt == staged.encode().bt) << "staged and unstaged maps differ at " << res << " m";
    // Taken out again (its leaves walked anew: the staged ones went with the set()).
    staged.remove("r2");
    plain.remove("r2");
    EXPECT_TRUE(plain.encode().bt == staged.encode().bt) << res;
  }
}

TEST_F(GlobalFusionTest, FinerMapsAreResampledAndProvenanceNamesEachRobot) {
  const Robot r1 = cut(*world_, "r1", -20, -2, 0.4);
  const Robot r2 = cut(*world_, "r2", -8, 6, 1.1);
  GlobalFusion g(0.2);  // coarser than the maps (0.08 m): fine leaves vote per voxel
  ASSERT_TRUE(g.set("r1", r1.map, T_global(r1)).ok);
  ASSERT_TRUE(g.set("r2", r2.map, T_global(r2)).ok);
  ASSERT_TRUE(g.set("r2", cut(*world_, "r2", -8, 12, 1.1).map, T_global(r2)).ok);
  ASSERT_TRUE(g.set("r2", r2.map, T_global(r2)).ok);
  GlobalFusion fresh(0.2);
  ASSERT_TRUE(fresh.set("r2", r2.map, T_global(r2)).ok);
  ASSERT_TRUE(fresh.set("r1", r1.map, T_global(r1)).ok);
  expect_same_voxels(*g.tree(), *fresh.tree());

  const Provenance p = g.provenance();
  ASSERT_EQ(p.robots.size(), 2U);
  EXPECT_EQ(p.robots[0].name, "r1");
  EXPECT_TRUE(p.robots[1].T_global_robot.isApprox(T_global(r2)));
  std::size_t by[2] = {0, 0};
  const auto tree = g.tree();
  for (const auto& [key, owner] : p.owner) {
    ASSERT_LT(owner.robot, 2U);
    ++by[owner.robot];
    const octomap::OcTreeNode* n = tree->search(key);
    ASSERT_NE(n, nullptr);  // every owned voxel is in the map
  }
  EXPECT_GT(by[0], 1000U);
  EXPECT_GT(by[1], 1000U);
}

}  // namespace
}  // namespace mapmerge
