// The client library (Fast DDS and Cyclone DDS) against a stand-in server on loopback: map
// updates arrive numbered, stamped and decodable; poses and global maps come back through
// callbacks and polling; a client started before the server connects when it appears; losing
// the server neither crashes nor blocks the client.

#include <atomic>
#include <chrono>
#include <mutex>
#include <thread>

#include <gtest/gtest.h>
#include <octomap/OcTree.h>

#include "dds_test_env.hpp"
#include "fake_server.hpp"
#include "mapmerge/client/client.hpp"
#include "mapmerge/map/map_codec.hpp"
#include "mapmerge/map/map_io.hpp"

namespace mapmerge {
namespace {

using namespace std::chrono_literals;
using client::Vendor;

constexpr auto kDelivery = 20s;  ///< generous bound for loopback delivery on a loaded machine

std::unique_ptr<octomap::OcTree> sample_tree(const char* name = "fr_079.bt") {
  return read_octree_file(std::string(MAPMERGE_DATA_DIR) + "/" + name);
}

template <class Pred>
bool eventually(Pred&& pred, std::chrono::milliseconds timeout = kDelivery) {
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  while (std::chrono::steady_clock::now() < deadline) {
    if (pred()) return true;
    std::this_thread::sleep_for(20ms);
  }
  return pred();
}

/// The tree a payload decodes to must serialise to the same bytes as the original.
void expect_same_tree(const octomap::OcTree& a, const octomap::OcTree& b) {
  EXPECT_EQ(a.size(), b.size());
  EXPECT_DOUBLE_EQ(a.getResolution(), b.getResolution());
  EXPECT_EQ(encode_map(a, Encoding::kOctomapBt), encode_map(b, Encoding::kOctomapBt));
}

class ClientVsFakeServer : public ::testing::TestWithParam<Vendor> {
 protected:
  client::Options options(const std::string& robot) const {
    client::Options o;
    o.robot_id = robot;
    o.domain = test::dds_domain();
    return o;  // profile "local": 127.0.0.1 only
  }
  std::unique_ptr<Client> make(const std::string& robot) { return make_client(options(robot), GetParam()); }
};

TEST_P(ClientVsFakeServer, PublishedUpdatesArriveNumberedStampedAndDecodable) {
  test::FakeServer server(test::dds_domain());
  server.listen_to("r1");
  auto robot = make("r1");
  EXPECT_EQ(robot->vendor(), GetParam());
  const auto tree = sample_tree();
  const auto before = std::chrono::system_clock::now();
  const client::PublishResult r1 = robot->publish(*tree);
  ASSERT_TRUE(r1.queued) << r1.error;
  EXPECT_EQ(r1.sequence_number, 1u);
  EXPECT_EQ(r1.encoding, "octomap-bt");

  const auto update = server.take_map("r1", kDelivery);
  ASSERT_TRUE(update) << "no map update reached the server";
  EXPECT_EQ(update->robot_id(), "r1");
  EXPECT_EQ(update->session_id(), robot->session_id());
  EXPECT_EQ(update->session_id().size(), 16u);
  EXPECT_EQ(update->sequence_number(), 1u);
  EXPECT_EQ(update->frame_id(), "r1/map");
  EXPECT_EQ(update->encoding(), "octomap-bt");
  EXPECT_DOUBLE_EQ(update->resolution(), tree->getResolution());
  EXPECT_EQ(update->data().size(), r1.bytes);
  const double stamp = update->stamp().sec() + 1e-9 * update->stamp().nanosec();
  const double now = std::chrono::duration<double>(before.time_since_epoch()).count();
  EXPECT_NEAR(stamp, now, 10.0);
  DecodeResult decoded = decode_map(update->data(), update->encoding(), DecodeLimits{});
  ASSERT_TRUE(decoded.ok()) << decoded.reason;
  expect_same_tree(*decoded.tree, *tree);

  // The next update is numbered one higher in the same session.
  ASSERT_TRUE(robot->flush(5s));
  const client::PublishResult r2 = robot->publish(*tree);
  EXPECT_EQ(r2.sequence_number, 2u);
  const auto second = server.take_map("r1", kDelivery);
  ASSERT_TRUE(second);
  EXPECT_EQ(second->sequence_number(), 2u);
  EXPECT_EQ(second->session_id(), robot->session_id());
}

TEST_P(ClientVsFakeServer, ZstdUpdatesAreSmallerAndDecodeToTheSameTree) {
  test::FakeServer server(test::dds_domain());
  server.listen_to("r2");
  auto o = options("r2");
  o.zstd = true;
  auto robot = make_client(o, GetParam());
  const auto tree = sample_tree("geb079.bt");
  const auto r = robot->publish(*tree);
  ASSERT_TRUE(r.queued) << r.error;
  EXPECT_EQ(r.encoding, "octomap-bt+zstd");
  EXPECT_LT(r.bytes, encode_map(*tree, Encoding::kOctomapBt).size());
  const auto update = server.take_map("r2", kDelivery);
  ASSERT_TRUE(update);
  EXPECT_EQ(update->encoding(), "octomap-bt+zstd");
  DecodeResult decoded = decode_map(update->data(), update->encoding(), DecodeLimits{});
  ASSERT_TRUE(decoded.ok()) << decoded.reason;
  expect_same_tree(*decoded.tree, *tree);
}

TEST_P(ClientVsFakeServer, PosesAndGlobalMapReachCallbacksAndPolling) {
  test::FakeServer server(test::dds_domain());
  auto robot = make("r1");
  std::mutex mutex;
  std::vector<client::Pose> own, all;
  std::shared_ptr<const client::GlobalMap> map_cb;
  robot->on_own_pose([&](const client::Pose& p) {
    std::lock_guard<std::mutex> lock(mutex);
    own.push_back(p);
  });
  robot->on_pose([&](const client::Pose& p) {
    std::lock_guard<std::mutex> lock(mutex);
    all.push_back(p);
  });
  robot->on_global_map([&](const std::shared_ptr<const client::GlobalMap>& m) {
    std::lock_guard<std::mutex> lock(mutex);
    map_cb = m;
  });
  ASSERT_TRUE(robot->wait_for_server(kDelivery));

  const double s = std::sqrt(0.5);  // 90 degrees about z
  ASSERT_TRUE(server.publish_pose(
      test::FakeServer::make_pose("r1", mapmerge::POSE_ALIGNED, {1.0, 2.0, 3.0}, {0.0, 0.0, s, s}, 7)));
  ASSERT_TRUE(server.publish_pose(
      test::FakeServer::make_pose("r2", mapmerge::POSE_UNKNOWN, {0.0, 0.0, 0.0}, {0.0, 0.0, 0.0, 1.0}, 7)));
  const auto tree = sample_tree("fr_078_tidyup.bt");
  ASSERT_TRUE(server.publish_global(encode_map(*tree, Encoding::kOctomapBt), "octomap-bt", 7, {"r1"}));

  ASSERT_TRUE(eventually([&] { return robot->poses().size() == 2 && robot->global_map() != nullptr; }));
  const auto mine = robot->own_pose();
  ASSERT_TRUE(mine);
  EXPECT_EQ(mine->status, client::PoseStatus::kAligned);
  EXPECT_EQ(mine->global_version, 7u);
  EXPECT_EQ(mine->global_frame_id, "global");
  EXPECT_EQ(mine->robot_frame_id, "r1/map");
  EXPECT_DOUBLE_EQ(mine->fitness, 0.02);
  const auto m = mine->matrix();  // row-major: x -> y, y -> -x
  const std::array<double, 16> expected{0, -1, 0, 1, 1, 0, 0, 2, 0, 0, 1, 3, 0, 0, 0, 1};
  for (int i = 0; i < 16; ++i) EXPECT_NEAR(m[i], expected[i], 1e-12) << "element " << i;
  const auto other = robot->pose("r2");
  ASSERT_TRUE(other);
  EXPECT_EQ(other->status, client::PoseStatus::kUnknown);
  EXPECT_FALSE(robot->pose("r9"));

  const auto global = robot->global_map();
  EXPECT_EQ(global->version, 7u);
  EXPECT_EQ(global->frame_id, "global");
  ASSERT_EQ(global->contributors.size(), 1u);
  EXPECT_EQ(global->contributors[0].robot_id, "r1");
  expect_same_tree(*global->tree, *tree);

  ASSERT_TRUE(eventually([&] {
    std::lock_guard<std::mutex> lock(mutex);
    return own.size() == 1 && all.size() == 2 && map_cb != nullptr;
  }));
  std::lock_guard<std::mutex> lock(mutex);
  EXPECT_EQ(own[0].robot_id, "r1");
  EXPECT_EQ(map_cb->version, 7u);
  EXPECT_EQ(robot->statistics().poses_received, 2u);
  EXPECT_EQ(robot->statistics().global_maps_received, 1u);
}

TEST_P(ClientVsFakeServer, LateCallbackGetsCurrentStateOnce) {
  test::FakeServer server(test::dds_domain());
  auto robot = make("r3");
  ASSERT_TRUE(server.publish_pose(
      test::FakeServer::make_pose("r3", mapmerge::POSE_ALIGNED, {0.5, 0.0, 0.0}, {0.0, 0.0, 0.0, 1.0}, 2)));
  ASSERT_TRUE(eventually([&] { return robot->own_pose().has_value(); }));
  std::atomic<int> calls{0};
  robot->on_own_pose([&](const client::Pose& p) {
    EXPECT_EQ(p.global_version, 2u);
    ++calls;
  });
  ASSERT_TRUE(eventually([&] { return calls == 1; }));
  std::this_thread::sleep_for(300ms);
  EXPECT_EQ(calls, 1);
}

TEST_P(ClientVsFakeServer, ClientStartedBeforeServerConnectsWhenItAppears) {
  auto robot = make("r4");
  std::atomic<int> connections{0};
  robot->on_server_connection([&](bool up) { connections += up ? 1 : 0; });
  EXPECT_FALSE(robot->wait_for_server(300ms));
  EXPECT_FALSE(robot->server_connected());
  const auto tree = sample_tree("geb079.bt");
  ASSERT_TRUE(robot->publish(*tree).queued);  // nobody listens yet: kept for late joiners

  test::FakeServer server(test::dds_domain());
  server.listen_to("r4");
  ASSERT_TRUE(robot->wait_for_server(kDelivery));
  const auto update = server.take_map("r4", kDelivery);
  ASSERT_TRUE(update) << "transient-local did not deliver the earlier update";
  EXPECT_EQ(update->sequence_number(), 1u);
  // On connecting, the client asks the server for the current state.
  const auto request = server.take_request(kDelivery);
  ASSERT_TRUE(request);
  EXPECT_EQ(request->requester(), "r4");
  EXPECT_TRUE(eventually([&] { return connections == 1; }));
}

TEST_P(ClientVsFakeServer, LosingTheServerNeitherCrashesNorBlocks) {
  auto robot = make("r5");
  std::atomic<int> lost{0}, connected{0};
  robot->on_server_connection([&](bool up) { ++(up ? connected : lost); });
  const auto tree = sample_tree("geb079.bt");
  {
    test::FakeServer server(test::dds_domain());
    server.listen_to("r5");
    ASSERT_TRUE(robot->wait_for_server(kDelivery));
    ASSERT_TRUE(robot->publish(*tree).queued);
    ASSERT_TRUE(server.take_map("r5", kDelivery));
    ASSERT_TRUE(server.publish_pose(
        test::FakeServer::make_pose("r5", mapmerge::POSE_ALIGNED, {0, 0, 0}, {0, 0, 0, 1}, 1)));
    ASSERT_TRUE(eventually([&] { return robot->own_pose().has_value(); }));
  }  // the server goes away (a clean leave; a crash is noticed after the lease duration)
  ASSERT_TRUE(eventually([&] { return !robot->server_connected(); }));
  EXPECT_TRUE(eventually([&] { return lost == 1; }));
  // Publishing without a server returns at once and the last pose is kept.
  for (int i = 0; i < 5; ++i) {
    const auto start = std::chrono::steady_clock::now();
    ASSERT_TRUE(robot->publish(*tree).queued);
    EXPECT_LT(std::chrono::steady_clock::now() - start, 1s);
  }
  const auto flush_start = std::chrono::steady_clock::now();
  robot->flush(200ms);  // nobody acknowledges: bounded by its timeout (+ one write's blocking)
  EXPECT_LT(std::chrono::steady_clock::now() - flush_start, 2s);
  ASSERT_TRUE(robot->own_pose());
  EXPECT_EQ(robot->own_pose()->status, client::PoseStatus::kAligned);

  // A new server (a restart) gets the latest update.
  test::FakeServer again(test::dds_domain());
  again.listen_to("r5");
  ASSERT_TRUE(robot->wait_for_server(kDelivery));
  const auto update = again.take_map("r5", kDelivery);
  ASSERT_TRUE(update);
  EXPECT_GE(update->sequence_number(), 2u);
  EXPECT_TRUE(eventually([&] { return connected == 2; }));
}

TEST_P(ClientVsFakeServer, ConcurrentPublishersNeverSendANumberBackwards) {
  test::FakeServer server(test::dds_domain());
  server.listen_to("r7");
  auto robot = make("r7");
  octomap::OcTree tree(0.1);
  tree.updateNode(octomap::point3d(1.0f, 1.0f, 1.0f), true);
  constexpr int kPerThread = 25;
  std::vector<std::thread> publishers;
  for (int t = 0; t < 2; ++t) {
    publishers.emplace_back([&] {
      for (int i = 0; i < kPerThread; ++i) ASSERT_TRUE(robot->publish(tree).queued);
    });
  }
  for (auto& t : publishers) t.join();
  ASSERT_TRUE(robot->flush(10s));
  // Keep-last-1 state topic: the server may miss intermediate updates, never see one go back.
  std::uint64_t last = 0;
  while (last < 2 * kPerThread) {
    const auto update = server.take_map("r7", kDelivery);
    ASSERT_TRUE(update) << "last sequence number seen: " << last;
    EXPECT_GT(update->sequence_number(), last);
    last = update->sequence_number();
  }
  EXPECT_EQ(last, std::uint64_t(2 * kPerThread));
  const auto stats = robot->statistics();
  EXPECT_EQ(stats.updates_published + stats.updates_coalesced, std::uint64_t(2 * kPerThread));
  EXPECT_EQ(stats.write_failures, 0u);
}

TEST_P(ClientVsFakeServer, RepublishedGlobalMapIsReportedOnce) {
  test::FakeServer server(test::dds_domain());
  auto robot = make("r8");
  std::atomic<int> maps{0};
  std::atomic<std::uint64_t> last_version{0};
  robot->on_global_map([&](const std::shared_ptr<const client::GlobalMap>& m) {
    ++maps;
    last_version = m->version;
  });
  const auto tree = sample_tree("geb079.bt");
  const auto bytes = encode_map(*tree, Encoding::kOctomapBt);
  ASSERT_TRUE(server.publish_global(bytes, "octomap-bt", 5, {"r8"}));
  ASSERT_TRUE(eventually([&] { return maps == 1; }));
  for (int i = 0; i < 3; ++i) {  // the server's periodic republish of the same version
    ASSERT_TRUE(server.publish_global(bytes, "octomap-bt", 5, {"r8"}));
    std::this_thread::sleep_for(100ms);
  }
  ASSERT_TRUE(server.publish_global(bytes, "octomap-bt", 6, {"r8"}));
  ASSERT_TRUE(eventually([&] { return last_version == 6u; }));
  EXPECT_EQ(maps, 2);
  EXPECT_EQ(robot->statistics().global_maps_received, 2u);
}

TEST_P(ClientVsFakeServer, InvalidGlobalMapIsRejectedWithAWarning) {
  test::FakeServer server(test::dds_domain());
  auto robot = make("r6");
  std::mutex mutex;
  std::vector<std::string> warnings;
  robot->on_warning([&](const std::string& w) {
    std::lock_guard<std::mutex> lock(mutex);
    warnings.push_back(w);
  });
  std::vector<std::uint8_t> junk(5000, 0x41);
  ASSERT_TRUE(server.publish_global(junk, "octomap-bt", 3, {}));
  ASSERT_TRUE(eventually([&] { return robot->statistics().global_maps_rejected == 1; }));
  EXPECT_EQ(robot->global_map(), nullptr);
  std::lock_guard<std::mutex> lock(mutex);
  ASSERT_FALSE(warnings.empty());
  EXPECT_NE(warnings[0].find("global map version 3 rejected"), std::string::npos) << warnings[0];
}

TEST_P(ClientVsFakeServer, ObserverCannotPublishAndBadOptionsThrow) {
  auto observer = make("");
  const auto tree = sample_tree("geb079.bt");
  const auto r = observer->publish(*tree);
  EXPECT_FALSE(r.queued);
  EXPECT_FALSE(r.error.empty());
  EXPECT_THROW(make("9bad"), client::ClientError);
  auto o = options("r1");
  o.profile = "nonsense";
  EXPECT_THROW(make_client(o, GetParam()), client::ClientError);
  EXPECT_FALSE(client::check_options(o).empty());
  EXPECT_TRUE(client::check_options(options("r1")).empty());
}

INSTANTIATE_TEST_SUITE_P(Vendors, ClientVsFakeServer, ::testing::Values(Vendor::kFastdds, Vendor::kCyclone),
                         [](const auto& param_info) { return std::string(client::to_string(param_info.param)); });

}  // namespace
}  // namespace mapmerge
