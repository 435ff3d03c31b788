// DDS Security with real participants on loopback (the `local` profile) and keystores made by
// scripts/make-keystore: authenticated robots reach the server byte for byte; strangers,
// forged or stolen permissions, revoked robots and robots writing on another robot's topic are
// refused; secured Cyclone DDS and Fast DDS participants interoperate both ways; map bytes
// never cross loopback in clear text. Negative checks always run next to a positive control on
// the same topic, so "nothing arrived" cannot pass just because discovery had not finished.

#include <algorithm>
#include <atomic>
#include <chrono>
#include <fstream>
#include <iterator>
#include <random>
#include <thread>
#include <vector>

#include <arpa/inet.h>
#include <linux/if_ether.h>
#include <linux/if_packet.h>
#include <net/if.h>
#include <sys/socket.h>
#include <unistd.h>

#include <gtest/gtest.h>

#include "dds_test_env.hpp"
#include "mapmerge/wire/cyclone.hpp"
#include "mapmerge/wire/fastdds.hpp"
#include "mapmerge/wire/topics.hpp"
#include "mapmerge_cyclone/mapmerge.h"
#include "mapmerge_fastdds/mapmergePubSubTypes.h"
#include "mapmerge_fastdds/ros2_msgsPubSubTypes.h"
#include "secure_test_env.hpp"

namespace mapmerge::test {
namespace {

namespace fdds = eprosima::fastdds::dds;
using namespace std::chrono_literals;
using wire::CycloneParticipant;
using wire::FastddsParticipant;
using wire::ParticipantOptions;
using wire::SecurityOptions;
using wire::TopicKind;

constexpr auto kDeliveryTimeout = 30000ms;  ///< bound on a wanted delivery (discovery + handshake)
constexpr auto kQuietPeriod = 3000ms;       ///< after the control delivered: how long intruders get

std::vector<uint8_t> sample_map() {
  std::ifstream in(std::string(MAPMERGE_DATA_DIR) + "/fr_079.bt", std::ios::binary);
  EXPECT_TRUE(in);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

mapmerge::MapUpdate map_update(const std::string& robot, const std::string& session, std::vector<uint8_t> bytes) {
  mapmerge::MapUpdate u;
  u.robot_id(robot);
  u.session_id(session);
  u.sequence_number(1);
  u.frame_id(robot + "/map");
  u.resolution(0.05);
  u.encoding("octomap-bt");
  u.data(std::move(bytes));
  return u;
}

mapmerge::GlobalMap global_map(const std::string& frame, uint64_t version) {
  mapmerge::GlobalMap g;
  g.version(version);
  g.frame_id(frame);
  g.resolution(0.05);
  g.encoding("octomap-bt");
  g.data({1, 2, 3, 4});
  return g;
}

/// Every sample a Fast DDS reader has now.
template <class Sample>
std::vector<Sample> fast_take_all(fdds::DataReader* reader) {
  std::vector<Sample> out;
  Sample s;
  fdds::SampleInfo info;
  while (reader->take_next_sample(&s, &info) == ReturnCode_t::RETCODE_OK) {
    if (info.valid_data) out.push_back(s);
  }
  return out;
}

/// Waits up to kDeliveryTimeout for the first valid sample.
template <class Sample>
bool fast_take_one(fdds::DataReader* reader, Sample& out) {
  return eventually(
      [&] {
        fdds::SampleInfo info;
        return reader->take_next_sample(&out, &info) == ReturnCode_t::RETCODE_OK && info.valid_data;
      },
      kDeliveryTimeout);
}

int matched(fdds::DataWriter* w) {
  fdds::PublicationMatchedStatus st;
  w->get_publication_matched_status(st);
  return st.total_count;
}
int matched(fdds::DataReader* r) {
  fdds::SubscriptionMatchedStatus st;
  r->get_subscription_matched_status(st);
  return st.total_count;
}

class Security : public ::testing::Test {
 protected:
  static void SetUpTestSuite() { keys_ = new SecureKeystores(); }
  static void TearDownTestSuite() {
    delete keys_;
    keys_ = nullptr;
  }

  static ParticipantOptions options(const std::string& name, SecurityOptions security) {
    ParticipantOptions o;
    o.domain = dds_domain();
    o.name = name;
    o.security = std::move(security);
    return o;
  }
  static SecurityOptions trusted(const std::string& enclave) { return {keys_->trusted(), enclave}; }
  static SecurityOptions server_identity() { return trusted("mapmerge_server"); }

  static SecureKeystores* keys_;
};
SecureKeystores* Security::keys_ = nullptr;

// --- an authenticated robot is merged -------------------------------------------------------

TEST_F(Security, AuthenticatedRobotMapReachesServerByteIdentical) {
  const auto bytes = sample_map();
  ASSERT_GT(bytes.size(), 100000u);
  FastddsParticipant server(options("server", server_identity()));
  auto* reader = server.create_reader(server.topic<mapmerge::MapUpdatePubSubType>(wire::map_topic("r1")),
                                      TopicKind::State);
  FastddsParticipant robot(options("r1", trusted("r1")));
  auto* writer = robot.create_writer(robot.topic<mapmerge::MapUpdatePubSubType>(wire::map_topic("r1")),
                                     TopicKind::State);
  auto update = map_update("r1", "s-1", bytes);
  ASSERT_TRUE(writer->write(&update));

  mapmerge::MapUpdate received;
  ASSERT_TRUE(fast_take_one(reader, received)) << "the authenticated robot's map never reached the server";
  EXPECT_EQ(received.robot_id(), "r1");
  EXPECT_EQ(received.session_id(), "s-1");
  EXPECT_EQ(received.data(), bytes);
}

TEST_F(Security, MisconfiguredSecurityFailsInsteadOfRunningInsecure) {
  EXPECT_THROW(FastddsParticipant(options("nobody", trusted("no_such_robot"))), wire::DdsError);
  EXPECT_THROW(CycloneParticipant(dds_domain(), wire::ProfileSpec{}, trusted("no_such_robot")), wire::CycloneError);
  EXPECT_THROW(FastddsParticipant(options("nowhere", SecurityOptions{"/nonexistent", "r1"})), wire::DdsError);
}

// --- a participant without a valid certificate is not matched -------------------------------

TEST_F(Security, ParticipantsWithoutValidIdentityAreNotMatched) {
  FastddsParticipant server(options("server", server_identity()));
  auto* map_reader = server.create_reader(server.topic<mapmerge::MapUpdatePubSubType>(wire::map_topic("r1")),
                                          TopicKind::State);
  auto* global_writer = server.create_writer(server.topic<mapmerge::GlobalMapPubSubType>(wire::kGlobalMapTopic),
                                             TopicKind::State);
  auto global = global_map("global", 1);
  ASSERT_TRUE(global_writer->write(&global));

  // Strangers: no security at all, and a certificate of another CA with a look-alike name.
  FastddsParticipant plain(options("plain-r1", SecurityOptions{}));
  FastddsParticipant stranger(options("other-ca-r1", SecurityOptions{keys_->other_ca(), "r1"}));
  std::vector<fdds::DataWriter*> intruder_writers;
  std::vector<fdds::DataReader*> intruder_readers;
  for (FastddsParticipant* p : {&plain, &stranger}) {
    auto* w = p->create_writer(p->topic<mapmerge::MapUpdatePubSubType>(wire::map_topic("r1")), TopicKind::State);
    auto fake = map_update("r1", "intruder", {0xde, 0xad});
    ASSERT_TRUE(w->write(&fake));
    intruder_writers.push_back(w);
    intruder_readers.push_back(
        p->create_reader(p->topic<mapmerge::GlobalMapPubSubType>(wire::kGlobalMapTopic), TopicKind::State));
  }

  // Control: the real r1 gets through in both directions.
  FastddsParticipant robot(options("r1", trusted("r1")));
  auto* writer = robot.create_writer(robot.topic<mapmerge::MapUpdatePubSubType>(wire::map_topic("r1")),
                                     TopicKind::State);
  auto* global_reader =
      robot.create_reader(robot.topic<mapmerge::GlobalMapPubSubType>(wire::kGlobalMapTopic), TopicKind::State);
  auto real = map_update("r1", "real", {1, 2, 3});
  ASSERT_TRUE(writer->write(&real));
  mapmerge::MapUpdate first;
  ASSERT_TRUE(fast_take_one(map_reader, first)) << "control: the trusted r1 never reached the server";
  mapmerge::GlobalMap got_global;
  ASSERT_TRUE(fast_take_one(global_reader, got_global)) << "control: the trusted r1 never got the global map";

  // The strangers had as long as the trusted robot, and now some more.
  std::vector<mapmerge::MapUpdate> at_server{first};
  eventually(
      [&] {
        for (auto& s : fast_take_all<mapmerge::MapUpdate>(map_reader)) at_server.push_back(s);
        return false;
      },
      kQuietPeriod);
  for (const auto& s : at_server) EXPECT_EQ(s.session_id(), "real") << "an intruder's map reached the server";
  EXPECT_EQ(matched(map_reader), 1) << "the server matched a writer other than the trusted r1";
  EXPECT_EQ(matched(global_writer), 1) << "the server's global map matched a reader other than the trusted r1";
  for (auto* w : intruder_writers) EXPECT_EQ(matched(w), 0) << "an intruder's writer was matched";
  for (auto* r : intruder_readers) {
    EXPECT_EQ(matched(r), 0) << "an intruder's reader was matched";
    EXPECT_TRUE(fast_take_all<mapmerge::GlobalMap>(r).empty()) << "an intruder read the global map";
  }
}

// --- robot r1 trying to publish on r2's topic is refused ------------------------------------

TEST_F(Security, RobotCannotWriteAnotherRobotsTopicOrTheServersFastdds) {
  FastddsParticipant robot(options("r1", trusted("r1")));
  EXPECT_NO_THROW(robot.create_writer(robot.topic<mapmerge::MapUpdatePubSubType>(wire::map_topic("r1")),
                                      TopicKind::State))
      << "control: r1 may write its own map";
  EXPECT_NO_THROW(robot.create_reader(robot.topic<mapmerge::GlobalMapPubSubType>(wire::kGlobalMapTopic),
                                      TopicKind::State))
      << "control: r1 may read the global map";
  EXPECT_THROW(robot.create_writer(robot.topic<mapmerge::MapUpdatePubSubType>(wire::map_topic("r2")),
                                   TopicKind::State),
               wire::DdsError)
      << "r1 wrote on r2's map topic";
  EXPECT_THROW(robot.create_writer(robot.topic<mapmerge::GlobalMapPubSubType>(wire::kGlobalMapTopic),
                                   TopicKind::State),
               wire::DdsError)
      << "r1 wrote the global map";
  EXPECT_THROW(robot.create_writer(robot.topic<mapmerge::RobotPosePubSubType>(wire::kPosesTopic), TopicKind::State),
               wire::DdsError)
      << "r1 wrote poses";
  EXPECT_THROW(robot.create_writer(robot.topic<mapmerge::ServerStatusPubSubType>(wire::kStatusTopic),
                                   TopicKind::State),
               wire::DdsError)
      << "r1 wrote the server's status";
  EXPECT_THROW(robot.create_writer(robot.topic<tf2_msgs::msg::dds_::TFMessage_PubSubType>(wire::kTfTopic),
                                   TopicKind::Event),
               wire::DdsError)
      << "r1 wrote tf";
  EXPECT_THROW(robot.create_writer(robot.topic<octomap_msgs::msg::dds_::Octomap_PubSubType>(wire::kRosGlobalMapTopic),
                                   TopicKind::State),
               wire::DdsError)
      << "r1 wrote the ROS 2 global map";
  EXPECT_THROW(robot.create_reader(robot.topic<mapmerge::MapUpdatePubSubType>(wire::map_topic("r2")),
                                   TopicKind::State),
               wire::DdsError)
      << "r1 read r2's map";
}

TEST_F(Security, RobotCannotWriteAnotherRobotsTopicCyclone) {
  CycloneParticipant robot(dds_domain(), wire::ProfileSpec{}, trusted("r1"));
  EXPECT_NO_THROW(robot.create_writer(robot.topic(&mapmerge_MapUpdate_desc, wire::map_topic("r1")), TopicKind::State))
      << "control: r1 may write its own map";
  EXPECT_THROW(robot.create_writer(robot.topic(&mapmerge_MapUpdate_desc, wire::map_topic("r2")), TopicKind::State),
               wire::CycloneError)
      << "r1 wrote on r2's map topic";
  EXPECT_THROW(robot.create_writer(robot.topic(&mapmerge_GlobalMap_desc, wire::kGlobalMapTopic), TopicKind::State),
               wire::CycloneError)
      << "r1 wrote the global map";
}

TEST_F(Security, Ros2OptionGrantsOnlyTheRobotsOwnNamespace) {
  const std::string dir = keys_->scratch("ros2");
  SecureKeystores::make(dir, "--robots r1,r2 --ros2");
  FastddsParticipant robot(options("r1", SecurityOptions{dir, "r1"}));
  auto writer_on = [&](const std::string& topic) {
    return robot.create_writer(robot.topic<mapmerge::MapUpdatePubSubType>(topic), TopicKind::Event);
  };
  EXPECT_NO_THROW(writer_on("ros_discovery_info"));
  EXPECT_NO_THROW(writer_on("rt/r1/cloud_in"));
  EXPECT_NO_THROW(writer_on("rr/r1/octomap_server/get_parametersReply"));
  EXPECT_THROW(writer_on("rt/r2/cloud_in"), wire::DdsError) << "r1 wrote in r2's namespace";
  EXPECT_THROW(writer_on("rt/mapmerge/global"), wire::DdsError) << "r1 wrote the global map";
}

TEST_F(Security, StolenPermissionsDoNotFitAnotherIdentity) {
  // r1's key with r2's genuine permissions: the subject differs, the participant is refused.
  EXPECT_THROW(FastddsParticipant(options("stolen", SecurityOptions{keys_->stolen(), "r1"})), wire::DdsError);
  EXPECT_NO_THROW(FastddsParticipant(options("r1", trusted("r1")))) << "control";
}

TEST_F(Security, ForgedPermissionsAreRefusedByPeers) {
  // r1's real key, with permissions granting the server's topics signed by another CA. Its own
  // stack accepts them (it trusts the forger's permissions CA), so only the peers can refuse.
  FastddsParticipant robot2(options("r2", trusted("r2")));
  auto* reader =
      robot2.create_reader(robot2.topic<mapmerge::GlobalMapPubSubType>(wire::kGlobalMapTopic), TopicKind::State);

  FastddsParticipant forged(options("forged-r1", SecurityOptions{keys_->forged(), "r1"}));
  fdds::DataWriter* forged_writer = nullptr;
  ASSERT_NO_THROW(forged_writer = forged.create_writer(
                      forged.topic<mapmerge::GlobalMapPubSubType>(wire::kGlobalMapTopic), TopicKind::State))
      << "the forged permissions should pass the forger's own local checks";
  auto fake = global_map("forged", 666);
  ASSERT_TRUE(forged_writer->write(&fake));

  FastddsParticipant server(options("server", server_identity()));
  auto* writer = server.create_writer(server.topic<mapmerge::GlobalMapPubSubType>(wire::kGlobalMapTopic),
                                      TopicKind::State);
  auto real = global_map("global", 1);
  ASSERT_TRUE(writer->write(&real));

  mapmerge::GlobalMap first;
  ASSERT_TRUE(fast_take_one(reader, first)) << "control: the server's global map never reached r2";
  std::vector<mapmerge::GlobalMap> got{first};
  eventually(
      [&] {
        for (auto& s : fast_take_all<mapmerge::GlobalMap>(reader)) got.push_back(s);
        return false;
      },
      kQuietPeriod);
  for (const auto& g : got) EXPECT_EQ(g.frame_id(), "global") << "a forged global map reached r2";
  EXPECT_EQ(matched(reader), 1);
  EXPECT_EQ(matched(forged_writer), 0) << "peers matched the forged writer";
}

TEST_F(Security, RevokedRobotIsRefused) {
  // r2 is stolen (the thief keeps a copy of its enclave), then revoked with make-keystore.
  const std::string dir = keys_->scratch("revocation");
  const std::string thief = keys_->scratch("thief");
  SecureKeystores::make(dir, "--robots r1,r2");
  SecureKeystores::splice(thief, "r2", dir, dir, {});
  SecureKeystores::make(dir, "--robots r1 --revoke r2");
  ASSERT_FALSE(fs::exists(dir + "/enclaves/r2")) << "the revoked enclave is still in the keystore";

  FastddsParticipant server(options("server", SecurityOptions{dir, "mapmerge_server"}));
  auto* r1_reader = server.create_reader(server.topic<mapmerge::MapUpdatePubSubType>(wire::map_topic("r1")),
                                         TopicKind::State);
  auto* r2_reader = server.create_reader(server.topic<mapmerge::MapUpdatePubSubType>(wire::map_topic("r2")),
                                         TopicKind::State);
  FastddsParticipant stolen(options("stolen-r2", SecurityOptions{thief, "r2"}));
  auto* stolen_writer = stolen.create_writer(stolen.topic<mapmerge::MapUpdatePubSubType>(wire::map_topic("r2")),
                                             TopicKind::State);
  auto fake = map_update("r2", "stolen", {6, 6, 6});
  ASSERT_TRUE(stolen_writer->write(&fake));
  FastddsParticipant robot(options("r1", SecurityOptions{dir, "r1"}));
  auto* writer = robot.create_writer(robot.topic<mapmerge::MapUpdatePubSubType>(wire::map_topic("r1")),
                                     TopicKind::State);
  auto real = map_update("r1", "real", {1, 2, 3});
  ASSERT_TRUE(writer->write(&real));

  mapmerge::MapUpdate got;
  ASSERT_TRUE(fast_take_one(r1_reader, got)) << "control: r1 (not revoked) never reached the server";
  std::vector<mapmerge::MapUpdate> from_r2;
  eventually(
      [&] {
        for (auto& x : fast_take_all<mapmerge::MapUpdate>(r2_reader)) from_r2.push_back(x);
        return false;
      },
      kQuietPeriod);
  EXPECT_TRUE(from_r2.empty()) << "the revoked robot's map reached the server";
  EXPECT_EQ(matched(r2_reader), 0);
  EXPECT_EQ(matched(stolen_writer), 0) << "the revoked robot was matched";
}

// --- a secured Cyclone DDS robot interoperates with the secured Fast DDS server -------------

TEST_F(Security, CycloneRobotMapReachesFastddsServerByteIdentical) {
  auto bytes = sample_map();
  FastddsParticipant server(options("server", server_identity()));
  auto* reader = server.create_reader(server.topic<mapmerge::MapUpdatePubSubType>(wire::map_topic("r2")),
                                      TopicKind::State);

  CycloneParticipant robot(dds_domain(), wire::ProfileSpec{}, trusted("r2"));
  const dds_entity_t writer =
      robot.create_writer(robot.topic(&mapmerge_MapUpdate_desc, wire::map_topic("r2")), TopicKind::State);
  mapmerge_MapUpdate update{};
  update.robot_id = const_cast<char*>("r2");
  update.session_id = const_cast<char*>("cyclone");
  update.sequence_number = 5;
  update.frame_id = const_cast<char*>("r2/map");
  update.resolution = 0.05;
  update.encoding = const_cast<char*>("octomap-bt");
  update.data._buffer = bytes.data();
  update.data._length = static_cast<uint32_t>(bytes.size());
  update.data._maximum = update.data._length;
  update.data._release = false;
  ASSERT_GE(dds_write(writer, &update), 0);

  mapmerge::MapUpdate received;
  ASSERT_TRUE(fast_take_one(reader, received)) << "the secured Cyclone robot's map never reached the server";
  EXPECT_EQ(received.robot_id(), "r2");
  EXPECT_EQ(received.sequence_number(), 5u);
  EXPECT_EQ(received.data(), bytes);
}

TEST_F(Security, FastddsServerGlobalMapReachesCycloneRobot) {
  FastddsParticipant server(options("server", server_identity()));
  auto* writer = server.create_writer(server.topic<mapmerge::GlobalMapPubSubType>(wire::kGlobalMapTopic),
                                      TopicKind::State);
  auto global = global_map("global", 42);
  global.data(sample_map());
  ASSERT_TRUE(writer->write(&global));

  CycloneParticipant robot(dds_domain(), wire::ProfileSpec{}, trusted("r1"));
  const dds_entity_t reader =
      robot.create_reader(robot.topic(&mapmerge_GlobalMap_desc, wire::kGlobalMapTopic), TopicKind::State);
  std::vector<uint8_t> received;
  uint64_t version = 0;
  const bool got = eventually(
      [&] {
        void* samples[1] = {nullptr};
        dds_sample_info_t info;
        const dds_return_t n = dds_take(reader, samples, &info, 1, 1);
        bool valid = false;
        if (n > 0 && info.valid_data) {
          const auto* g = static_cast<const mapmerge_GlobalMap*>(samples[0]);
          received.assign(g->data._buffer, g->data._buffer + g->data._length);
          version = g->version;
          valid = true;
        }
        if (n > 0) dds_return_loan(reader, samples, n);
        return valid;
      },
      kDeliveryTimeout);
  ASSERT_TRUE(got) << "the server's global map never reached the secured Cyclone robot";
  EXPECT_EQ(version, 42u);
  EXPECT_EQ(received, global.data());
}

TEST_F(Security, CycloneServerWorksWithFastddsRobot) {
  // make-keystore --server-vendor cyclone orders handshakes for a server on Cyclone DDS.
  const std::string keystore = keys_->cyclone_server();
  auto bytes = sample_map();
  CycloneParticipant server(dds_domain(), wire::ProfileSpec{}, SecurityOptions{keystore, "mapmerge_server"});
  const dds_entity_t reader =
      server.create_reader(server.topic(&mapmerge_MapUpdate_desc, wire::map_topic("r1")), TopicKind::State);
  FastddsParticipant robot(options("r1", SecurityOptions{keystore, "r1"}));
  auto* writer = robot.create_writer(robot.topic<mapmerge::MapUpdatePubSubType>(wire::map_topic("r1")),
                                     TopicKind::State);
  auto update = map_update("r1", "to-cyclone", bytes);
  ASSERT_TRUE(writer->write(&update));
  std::vector<uint8_t> received;
  const bool got = eventually(
      [&] {
        void* samples[1] = {nullptr};
        dds_sample_info_t info;
        const dds_return_t n = dds_take(reader, samples, &info, 1, 1);
        bool valid = false;
        if (n > 0 && info.valid_data) {
          const auto* u = static_cast<const mapmerge_MapUpdate*>(samples[0]);
          received.assign(u->data._buffer, u->data._buffer + u->data._length);
          valid = true;
        }
        if (n > 0) dds_return_loan(reader, samples, n);
        return valid;
      },
      kDeliveryTimeout);
  ASSERT_TRUE(got) << "the Fast DDS robot's map never reached the secured Cyclone server";
  EXPECT_EQ(received, bytes);
}

TEST(SecurityOptions, FromRos2Environment) {
  ::unsetenv("ROS_SECURITY_ENABLE");
  ::setenv("ROS_SECURITY_KEYSTORE", "/keys", 1);
  EXPECT_FALSE(SecurityOptions::from_environment("r1").enabled()) << "ROS_SECURITY_ENABLE unset must mean off";
  ::setenv("ROS_SECURITY_ENABLE", "true", 1);
  auto s = SecurityOptions::from_environment("r1");
  EXPECT_EQ(s.keystore, "/keys");
  EXPECT_EQ(s.enclave, "r1");
  ::setenv("ROS_SECURITY_ENCLAVE", "/r2", 1);
  EXPECT_EQ(SecurityOptions::from_environment("r1").enclave, "r2");
  for (const char* v : {"ROS_SECURITY_ENABLE", "ROS_SECURITY_KEYSTORE", "ROS_SECURITY_ENCLAVE"}) ::unsetenv(v);
}

// --- the keystore script ------------------------------------------------------------------------

std::string file_bytes(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

TEST_F(Security, KeystoreRerunKeepsIdentitiesAndAddsNames) {
  const std::string dir = keys_->scratch("rerun");
  SecureKeystores::make(dir, "--robots r1");
  const char* kept[] = {"public/ca.cert.pem", "private/ca.key.pem", "enclaves/governance.p7s",
                        "enclaves/r1/cert.pem", "enclaves/r1/key.pem", "enclaves/r1/permissions.p7s",
                        "enclaves/mapmerge_server/cert.pem", "enclaves/mapmerge_server/permissions.p7s"};
  std::vector<std::string> before;
  for (const char* f : kept) before.push_back(file_bytes(dir + "/" + f));
  SecureKeystores::make(dir, "--robots r1,r3");
  for (size_t i = 0; i < std::size(kept); ++i) {
    EXPECT_FALSE(before[i].empty()) << kept[i];
    EXPECT_EQ(file_bytes(dir + "/" + kept[i]), before[i]) << kept[i] << " changed on a re-run";
  }
  EXPECT_NO_THROW((void)SecurityOptions({dir, "r3"}).files()) << "r3 was not added";
  EXPECT_NE(file_bytes(dir + "/enclaves/r3/permissions.xml").find("rt/r3/mapmerge/map"), std::string::npos);
  EXPECT_EQ(file_bytes(dir + "/enclaves/r3/permissions.xml").find("rt/r1/"), std::string::npos);
}

// --- map payloads are encrypted on the wire ---------------------------------------------------

/// Captures every packet on the loopback interface (needs CAP_NET_RAW) and remembers whether
/// `marker` appeared in any of them.
class LoopbackSniffer {
 public:
  explicit LoopbackSniffer(std::vector<uint8_t> marker) : marker_(std::move(marker)) {
    fd_ = ::socket(AF_PACKET, SOCK_RAW, htons(ETH_P_ALL));
    if (fd_ < 0) return;
    sockaddr_ll addr{};
    addr.sll_family = AF_PACKET;
    addr.sll_protocol = htons(ETH_P_ALL);
    addr.sll_ifindex = static_cast<int>(if_nametoindex("lo"));
    timeval tv{0, 100000};
    const int buffer = 8 << 20;  // hold a whole map's burst (the kernel caps it at rmem_max)
    ::setsockopt(fd_, SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof tv);
    ::setsockopt(fd_, SOL_SOCKET, SO_RCVBUF, &buffer, sizeof buffer);
    if (addr.sll_ifindex == 0 || ::bind(fd_, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0) {
      ::close(fd_);
      fd_ = -1;
      return;
    }
    thread_ = std::thread([this] { run(); });
  }
  ~LoopbackSniffer() {
    finish();
    if (fd_ >= 0) ::close(fd_);
  }
  bool ok() const { return fd_ >= 0; }
  /// Processes the packets already captured (until the queue is empty, or for at most 2 s when
  /// other tests keep loopback busy), then stops.
  void finish() {
    stop_deadline_ = std::chrono::steady_clock::now() + 2s;
    stop_ = true;
    if (thread_.joinable()) thread_.join();
  }
  bool seen() const { return seen_; }
  size_t bytes() const { return bytes_; }

 private:
  void run() {
    std::vector<uint8_t> buf(1 << 16);
    for (;;) {
      const ssize_t n = ::recv(fd_, buf.data(), buf.size(), 0);
      if (stop_ && (n <= 0 || std::chrono::steady_clock::now() > stop_deadline_)) return;
      if (n <= 0) continue;
      bytes_ += static_cast<size_t>(n);
      if (std::search(buf.begin(), buf.begin() + n, marker_.begin(), marker_.end()) != buf.begin() + n) seen_ = true;
    }
  }
  std::vector<uint8_t> marker_;
  int fd_ = -1;
  std::chrono::steady_clock::time_point stop_deadline_;  ///< written before stop_ is set
  std::atomic<bool> stop_{false};
  std::atomic<bool> seen_{false};
  std::atomic<size_t> bytes_{0};
  std::thread thread_;
};

/// A 256 KiB payload with a random 24-byte marker every 4 KiB (so many copies sit wholly inside
/// one UDP fragment).
std::vector<uint8_t> marked_payload(std::vector<uint8_t>& marker) {
  std::random_device rd;
  marker.resize(24);
  for (auto& b : marker) b = static_cast<uint8_t>(rd());
  std::vector<uint8_t> payload(256 * 1024, 0x55);
  for (size_t at = 0; at + marker.size() < payload.size(); at += 4096) {
    std::copy(marker.begin(), marker.end(), payload.begin() + static_cast<std::ptrdiff_t>(at));
  }
  return payload;
}

/// Cyclone robot r2 -> Fast DDS server over UDP on loopback (Cyclone has no shared memory
/// here, so the bytes must cross `lo`). Returns whether the map arrived intact.
bool cyclone_to_fastdds(bool secure, std::vector<uint8_t> payload, const std::string& server_enclave_keystore) {
  ParticipantOptions so;
  so.domain = dds_domain();
  so.name = "server";
  if (secure) so.security = SecurityOptions{server_enclave_keystore, "mapmerge_server"};
  FastddsParticipant server(so);
  auto* reader = server.create_reader(server.topic<mapmerge::MapUpdatePubSubType>(wire::map_topic("r2")),
                                      TopicKind::State);
  CycloneParticipant robot(dds_domain(), wire::ProfileSpec{},
                           secure ? SecurityOptions{server_enclave_keystore, "r2"} : SecurityOptions{});
  const dds_entity_t writer =
      robot.create_writer(robot.topic(&mapmerge_MapUpdate_desc, wire::map_topic("r2")), TopicKind::State);
  mapmerge_MapUpdate update{};
  update.robot_id = const_cast<char*>("r2");
  update.session_id = const_cast<char*>("marked");
  update.frame_id = const_cast<char*>("r2/map");
  update.encoding = const_cast<char*>("octomap-bt");
  update.data._buffer = payload.data();
  update.data._length = static_cast<uint32_t>(payload.size());
  update.data._maximum = update.data._length;
  if (dds_write(writer, &update) < 0) return false;
  mapmerge::MapUpdate received;
  return fast_take_one(reader, received) && received.data() == payload;
}

TEST_F(Security, MapPayloadIsEncryptedOnTheWire) {
  std::vector<uint8_t> marker;
  const auto payload = marked_payload(marker);
  {
    LoopbackSniffer sniffer(marker);
    if (!sniffer.ok()) GTEST_SKIP() << "no CAP_NET_RAW: cannot capture loopback packets";
    // Control: without security the marker is visible, so the capture works.
    ASSERT_TRUE(cyclone_to_fastdds(false, payload, keys_->trusted())) << "control: plain map not delivered";
    sniffer.finish();
    ASSERT_TRUE(sniffer.seen()) << "control: the capture never saw the plain payload";
  }
  LoopbackSniffer sniffer(marker);
  ASSERT_TRUE(cyclone_to_fastdds(true, payload, keys_->trusted())) << "secured map not delivered";
  sniffer.finish();
  EXPECT_GE(sniffer.bytes(), payload.size()) << "the secured map did not cross loopback at all";
  EXPECT_FALSE(sniffer.seen()) << "map bytes crossed the network in clear text";
}

}  // namespace
}  // namespace mapmerge::test
