// The client with DDS Security (a keystore from scripts/make-keystore): authenticated robots of
// both vendors and an authenticated observer talk to a secure (stand-in) server; a client
// without an identity never sees it; a misconfigured keystore fails at construction.

#include <cstdlib>
#include <filesystem>
#include <thread>

#include <gtest/gtest.h>
#include <octomap/OcTree.h>

#include "dds_test_env.hpp"
#include "fake_server.hpp"
#include "mapmerge/client/client.hpp"

namespace mapmerge {
namespace {

using namespace std::chrono_literals;
namespace fs = std::filesystem;
using client::Vendor;

constexpr auto kSecureDelivery = 30s;  ///< handshakes make discovery slower

/// One keystore for the whole test program: server, robots r1 and r2, observer viewer1.
class Keystore : public ::testing::Environment {
 public:
  void SetUp() override {
    char tmpl[] = "/tmp/mapmerge-client-keystore-XXXXXX";
    ASSERT_NE(::mkdtemp(tmpl), nullptr);
    root = tmpl;
    const std::string cmd = std::string(MAPMERGE_MAKE_KEYSTORE) + " " + root + "/ks --robots r1,r2 --observers viewer1 >/dev/null";
    ASSERT_EQ(std::system(cmd.c_str()), 0) << cmd;
  }
  void TearDown() override { fs::remove_all(root); }
  static std::string keystore() { return root + "/ks"; }
  static inline std::string root;
};

template <class Pred>
bool eventually(Pred&& pred, std::chrono::milliseconds timeout) {
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  while (std::chrono::steady_clock::now() < deadline) {
    if (pred()) return true;
    std::this_thread::sleep_for(20ms);
  }
  return pred();
}

class SecureClient : public ::testing::TestWithParam<Vendor> {
 protected:
  client::Options options(const std::string& robot) const {
    client::Options o;
    o.robot_id = robot;
    o.domain = test::dds_domain();
    o.keystore = Keystore::keystore();
    return o;
  }
  static wire::SecurityOptions server_identity() { return {Keystore::keystore(), "mapmerge_server"}; }
};

TEST_P(SecureClient, AuthenticatedRobotAndObserverTalkToTheServer) {
  test::FakeServer server(test::dds_domain(), "", server_identity());
  server.listen_to("r1");
  auto robot = make_client(options("r1"), GetParam());
  auto observer_options = options("");
  observer_options.enclave = "viewer1";
  // An operator's observer, on Fast DDS: Cyclone DDS 0.10 applies one identity per domain and
  // process (the first participant's), so a second identity in this process must use Fast DDS.
  auto observer = make_client(observer_options, Vendor::kFastdds);
  ASSERT_TRUE(robot->wait_for_server(kSecureDelivery));

  octomap::OcTree tree(0.1);
  tree.updateNode(octomap::point3d(1.0f, 2.0f, 0.5f), true);
  ASSERT_TRUE(robot->publish(tree).queued);
  const auto update = server.take_map("r1", kSecureDelivery);
  ASSERT_TRUE(update) << "the authenticated robot's map never reached the server";
  EXPECT_EQ(update->session_id(), robot->session_id());

  ASSERT_TRUE(server.publish_pose(test::FakeServer::make_pose("r1", mapmerge::POSE_ALIGNED, {1, 2, 3}, {0, 0, 0, 1}, 2)));
  ASSERT_TRUE(eventually([&] { return robot->own_pose().has_value(); }, kSecureDelivery));
  ASSERT_TRUE(eventually([&] { return observer->pose("r1").has_value(); }, kSecureDelivery));
  EXPECT_EQ(observer->pose("r1")->status, client::PoseStatus::kAligned);
}

TEST_P(SecureClient, ClientWithoutIdentityNeverSeesTheSecureServer) {
  test::FakeServer server(test::dds_domain(), "", server_identity());
  auto o = options("r2");
  o.keystore.clear();
  ::unsetenv("ROS_SECURITY_ENABLE");
  auto plain = make_client(o, GetParam());
  EXPECT_FALSE(plain->wait_for_server(3s));
}

TEST_P(SecureClient, MisconfiguredSecurityFailsAtConstruction) {
  auto o = options("r9");  // no enclave r9 in the keystore
  EXPECT_FALSE(client::check_options(o).empty());
  EXPECT_THROW(make_client(o, GetParam()), client::ClientError);
  auto observer = options("");  // an observer must name its enclave
  EXPECT_FALSE(client::check_options(observer).empty());
}

INSTANTIATE_TEST_SUITE_P(Vendors, SecureClient, ::testing::Values(Vendor::kFastdds, Vendor::kCyclone),
                         [](const auto& param_info) { return std::string(client::to_string(param_info.param)); });

}  // namespace
}  // namespace mapmerge

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  ::testing::AddGlobalTestEnvironment(new mapmerge::Keystore);
  return RUN_ALL_TESTS();
}
