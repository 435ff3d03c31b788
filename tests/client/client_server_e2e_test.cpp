// The client library against the real mapmerge-server process: a Fast DDS robot started before
// the server connects once it appears; a Cyclone DDS robot with zstd payloads is aligned
// against it within tolerance of the ground truth; both receive the global map; a server
// killed and restarted on the same state is survived and rejoined.

#include <atomic>
#include <map>
#include <mutex>
#include <sstream>
#include <thread>

#include <gtest/gtest.h>
#include <octomap/OcTree.h>

#include "mapmerge/client/client.hpp"
#include "mapmerge/map/crop.hpp"
#include "mapmerge/map/map_io.hpp"
#include "server_fixture.hpp"

namespace mapmerge {
namespace {

using namespace std::chrono_literals;
constexpr auto kAlignment = 150s;  ///< first alignment of two Freiburg strips on 2 busy cores
constexpr auto kConnect = 30s;

template <class Pred>
bool eventually(Pred&& pred, std::chrono::milliseconds timeout) {
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  while (std::chrono::steady_clock::now() < deadline) {
    if (pred()) return true;
    std::this_thread::sleep_for(50ms);
  }
  return pred();
}

bool aligned(const Client& c) {
  const auto p = c.own_pose();
  return p && p->status == client::PoseStatus::kAligned;
}

class ClientServerE2E : public test::ServerFixture {};

TEST_F(ClientServerE2E, RobotsOfBothVendorsAreAlignedAndSurviveAServerRestart) {
  client::Options o1;
  o1.robot_id = "r1";
  o1.domain = test::dds_domain();
  Client r1(o1);  // Fast DDS, started before the server
  EXPECT_FALSE(r1.wait_for_server(200ms));
  const auto map1 = read_octree_file(map_path("r1"));
  ASSERT_TRUE(r1.publish(*map1).queued);

  start_server();
  ASSERT_TRUE(r1.wait_for_server(kConnect)) << server_log();

  client::Options o2 = o1;
  o2.robot_id = "r2";
  o2.zstd = true;
  CycloneClient r2(o2);
  const auto map2 = read_octree_file(map_path("r2"));
  ASSERT_TRUE(r2.publish(*map2).queued);

  ASSERT_TRUE(eventually([&] { return aligned(r1) && aligned(r2); }, kAlignment)) << server_log();
  for (const char* robot : {"r1", "r2"}) {
    const Client& c = std::string(robot) == "r1" ? static_cast<const Client&>(r1) : r2;
    const auto pose = c.own_pose();
    const auto error = test::pose_error(true_pose(robot), pose->matrix());
    EXPECT_LT(error.rotation_deg, kMaxRotationErrorDeg) << robot;
    EXPECT_LT(error.translation_m, kMaxTranslationErrorM) << robot;
    EXPECT_EQ(pose->global_frame_id, "global");
    EXPECT_EQ(pose->robot_frame_id, std::string(robot) + "/map");
  }
  // Each sees the other's pose, and the global map holding both robots.
  EXPECT_TRUE(eventually([&] { return r1.pose("r2") && r2.pose("r1"); }, kConnect));
  const std::uint64_t version = r2.own_pose()->global_version;
  ASSERT_TRUE(eventually([&] {
    const auto g = r1.global_map();
    return g && g->version >= version && g->contributors.size() == 2;
  }, kConnect)) << server_log();
  const auto global = r1.global_map();
  // Fused: more occupied space than r1's map alone (r2's strip overlaps r1's by under half).
  EXPECT_GT(test::occupied_volume(*global->tree), 1.2 * test::occupied_volume(*map1));
  ASSERT_TRUE(eventually([&] { return r2.global_map() && r2.global_map()->version >= version; }, kConnect));

  // The server crashes: the robots notice, keep their poses, and keep publishing without blocking.
  std::atomic<int> lost{0};
  r2.on_server_connection([&](bool up) { lost += up ? 0 : 1; });
  stop_server(SIGKILL);
  ASSERT_TRUE(eventually([&] { return !r1.server_connected() && !r2.server_connected(); }, 60s))
      << "a crashed server is noticed after the DDS lease duration";
  EXPECT_TRUE(eventually([&] { return lost >= 1; }, 5s));
  const auto start = std::chrono::steady_clock::now();
  ASSERT_TRUE(r2.publish(*map2).queued);
  EXPECT_LT(std::chrono::steady_clock::now() - start, 5s);
  EXPECT_TRUE(aligned(r1) && aligned(r2));

  // Restarted on the same state directory: both reconnect and get poses again.
  const auto before = r2.statistics().poses_received;
  start_server();
  ASSERT_TRUE(r1.wait_for_server(kConnect) && r2.wait_for_server(kConnect)) << server_log();
  ASSERT_TRUE(eventually([&] { return r2.statistics().poses_received > before && aligned(r2); }, kAlignment))
      << server_log();
}

/// Two trees node for node: same size, same structure, same log-odds (inner nodes too).
std::size_t differing_nodes(const octomap::OcTree& a, const octomap::OcTree& b) {
  if (a.size() != b.size()) return std::max(a.size(), b.size());
  std::size_t differing = 0;
  auto ib = b.begin_tree();
  for (auto ia = a.begin_tree(), end = a.end_tree(); ia != end; ++ia, ++ib) {
    differing += ia.getKey() != ib.getKey() || ia.getDepth() != ib.getDepth() || ia.isLeaf() != ib.isLeaf() ||
                 ia->getLogOdds() != ib->getLogOdds();
  }
  return differing;
}

TEST_F(ClientServerE2E, ObserversPatchTheGlobalMapFromItsChangedBlocksAsIfTheyDecodedIt) {
  // One robot (the reference: the global map is its map) shrinks and grows its map. Two
  // observers, one per vendor, let go of every map they get: they patch the next version from
  // the changed blocks. A third keeps every map it gets: it cannot patch in place and decodes
  // each version whole. All must hold the same trees, node for node.
  start_server();
  client::Options o;
  o.domain = test::dds_domain();
  Client fast_patcher(o);
  CycloneClient cyclone_patcher(o);
  Client keeper(o);
  std::mutex kept_mutex;
  std::map<std::uint64_t, std::shared_ptr<const client::GlobalMap>> kept;  // by version
  keeper.on_global_map([&](const std::shared_ptr<const client::GlobalMap>& g) {
    std::lock_guard<std::mutex> lock(kept_mutex);
    kept[g->version] = g;
  });
  o.robot_id = "r1";
  Client robot(o);
  const auto full = read_octree_file(map_path("r1"));
  double lo[3], hi[3];
  full->getMetricMin(lo[0], lo[1], lo[2]);
  full->getMetricMax(hi[0], hi[1], hi[2]);
  const auto shrunk = crop_and_transform(
      *full, Eigen::AlignedBox3d(Eigen::Vector3d(lo[0], lo[1], lo[2]), Eigen::Vector3d(lo[0] + 0.8 * (hi[0] - lo[0]), hi[1], hi[2])),
      Eigen::Isometry3d::Identity());
  const std::vector<const octomap::OcTree*> updates{full.get(), shrunk.get(), full.get(), shrunk.get()};
  for (std::size_t k = 0; k < updates.size(); ++k) {
    const std::uint64_t seq = robot.publish(*updates[k]).sequence_number;
    const auto holds = [&](const auto& c) {
      const auto g = c.global_map();
      return g && !g->contributors.empty() && g->contributors[0].sequence_number >= seq;
    };
    ASSERT_TRUE(eventually([&] { return holds(fast_patcher) && holds(cyclone_patcher) && holds(keeper); }, kAlignment))
        << "update " << k << "\n" << server_log();
    for (const Client* c : {static_cast<const Client*>(&fast_patcher), static_cast<const Client*>(&cyclone_patcher)}) {
      const auto mine = c->global_map();
      std::shared_ptr<const client::GlobalMap> theirs;
      ASSERT_TRUE(eventually([&] {
        std::lock_guard<std::mutex> lock(kept_mutex);
        const auto it = kept.find(mine->version);
        if (it != kept.end()) theirs = it->second;
        return theirs != nullptr;
      }, kConnect)) << "version " << mine->version;
      EXPECT_EQ(differing_nodes(*mine->tree, *theirs->tree), 0U) << client::to_string(c->vendor()) << ", update " << k;
    }
  }
  EXPECT_EQ(keeper.statistics().global_maps_patched, 0U) << "a held map is never patched in place";
  for (const Client* c : {static_cast<const Client*>(&fast_patcher), static_cast<const Client*>(&cyclone_patcher)}) {
    const auto st = c->statistics();
    EXPECT_GE(st.global_maps_patched, updates.size() - 1) << client::to_string(c->vendor()) << ": each change after the first map";
    EXPECT_EQ(st.global_deltas_rejected, 0U);
    EXPECT_EQ(st.global_maps_rejected, 0U);
  }
}

}  // namespace
}  // namespace mapmerge

namespace mapmerge {
namespace {

/// The CLIs as the demo runs them: two mapmerge-robot processes (Fast DDS, Cyclone + zstd) and
/// mapmerge-listen --until-aligned against the real server; the JSON poses match the truth and
/// the saved global map holds both robots.
TEST_F(ClientServerE2E, CliRobotsAndListenAgainstTheServer) {
  start_server();
  const std::string domain = std::to_string(test::dds_domain());
  test::ChildProcess r1(test::kBin + "mapmerge-robot", {"--id", "r1", "--map", map_path("r1"), "--domain", domain},
                        test::Logs::split((dir_ / "r1").string()));
  test::ChildProcess r2(test::kBin + "mapmerge-robot",
                        {"--id", "r2", "--map", map_path("r2"), "--domain", domain, "--vendor", "cyclone", "--zstd"},
                        test::Logs::split((dir_ / "r2").string()));
  const std::string global = (dir_ / "global.bt").string();
  test::ChildProcess listen(test::kBin + "mapmerge-listen",
                            {"--domain", domain, "--json", "--until-aligned", "2", "-o", global, "--timeout", "150"},
                            test::Logs::split((dir_ / "listen").string()));
  ASSERT_EQ(listen.wait(std::chrono::seconds(200)), 0) << listen.err() << server_log();

  std::map<std::string, nlohmann::json> latest;
  std::istringstream lines(listen.out());
  for (std::string line; std::getline(lines, line);) {
    const auto j = nlohmann::json::parse(line);
    latest[j["robot"]] = j;
  }
  for (const char* robot : {"r1", "r2"}) {
    ASSERT_TRUE(latest.count(robot)) << listen.out();
    EXPECT_EQ(latest[robot]["status"], "aligned");
    std::array<double, 16> estimate{};
    for (int i = 0; i < 16; ++i) estimate[i] = latest[robot]["T_global_robot"][i].get<double>();
    const auto error = test::pose_error(true_pose(robot), estimate);
    EXPECT_LT(error.rotation_deg, kMaxRotationErrorDeg) << robot;
    EXPECT_LT(error.translation_m, kMaxTranslationErrorM) << robot;
  }
  const auto saved = read_octree_file(global);
  const auto map1 = read_octree_file(map_path("r1"));
  EXPECT_GT(test::occupied_volume(*saved), 1.2 * test::occupied_volume(*map1));

  // Both robots print their pose and stop cleanly on SIGTERM.
  EXPECT_TRUE(r1.running() && r2.running());
  r1.signal(SIGTERM);
  r2.signal(SIGTERM);
  EXPECT_EQ(r1.wait(std::chrono::seconds(20)), 0) << r1.err();
  EXPECT_EQ(r2.wait(std::chrono::seconds(20)), 0) << r2.err();
  EXPECT_NE(r2.out().find("r2: pose aligned"), std::string::npos) << r2.out();
}

}  // namespace
}  // namespace mapmerge
