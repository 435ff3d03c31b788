// mapmerge-server with DDS Security: a keystore from scripts/make-keystore (made in a fresh
// temporary directory), authenticated robots merged and seen by an authenticated observer; a
// keystore without the server's enclave stops the server at once with a clear message.

#include <cstdlib>
#include <filesystem>

#include "server_fixture.hpp"

namespace mapmerge::test {
namespace {

/// Keystore `dir` with the server (enclave mapmerge_server), robots r1, r2 and observer viewer1.
void make_keystore(const std::string& dir) {
  const std::string cmd = std::string(MAPMERGE_MAKE_KEYSTORE) + " " + dir + " --robots r1,r2 --observers viewer1 >/dev/null";
  ASSERT_EQ(std::system(cmd.c_str()), 0) << cmd;
}

TEST_F(ServerFleet, SecuredServerMergesAuthenticatedRobots) {
  const std::string keystore = dir + "/keys";
  ASSERT_NO_FATAL_FAILURE(make_keystore(keystore));
  auto server = start_server({"--keystore", keystore});
  FleetListener op(domain, {}, wire::SecurityOptions{keystore, "viewer1"});
  std::vector<std::unique_ptr<RobotPublisher>> pubs;
  for (std::size_t i = 0; i < 2; ++i) {
    const std::string& id = fleet().robots[i].id;
    pubs.push_back(std::make_unique<RobotPublisher>(domain, id, wire::ProfileSpec{}, wire::SecurityOptions{keystore, id}));
    pubs.back()->publish(*fleet().robots[i].tree);
  }
  ASSERT_TRUE(op.wait_for([&] { return global_has(op, 2) && aligned(op, {"r1", "r2"}); }, kMergeTimeout))
      << server->log();
  EXPECT_NE(server->log().find("DDS security: keystore " + keystore), std::string::npos) << server->log();
  EXPECT_EQ(server->kill(SIGTERM), 0);
}

TEST_F(ServerFleet, KeystoreWithoutTheServersEnclaveIsAConfigurationError) {
  const std::string keystore = dir + "/keys";
  ASSERT_NO_FATAL_FAILURE(make_keystore(keystore));
  auto server = start_server({"--keystore", keystore, "--enclave", "no_such_server"});
  EXPECT_EQ(server->kill(0, std::chrono::seconds(30)), 2);  // signal 0: just wait for the exit
  EXPECT_NE(server->log().find("no_such_server"), std::string::npos) << server->log();
  auto missing = start_server({"--keystore", dir + "/no-keystore-here"});
  EXPECT_EQ(missing->kill(0, std::chrono::seconds(30)), 2);
}

}  // namespace
}  // namespace mapmerge::test
