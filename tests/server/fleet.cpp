#include "fleet.hpp"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <set>

#include <unistd.h>

#include <fastdds/dds/subscriber/SampleInfo.hpp>

#include "mapmerge/map/crop.hpp"
#include "mapmerge/map/map_codec.hpp"
#include "mapmerge/map/map_io.hpp"
#include "mapmerge/wire/topics.hpp"
#include "mapmerge_fastdds/mapmergePubSubTypes.h"
#include "mapmerge_fastdds/ros2_msgsPubSubTypes.h"

namespace mapmerge::test {
namespace fdds = eprosima::fastdds::dds;
using ReturnCode_t = eprosima::fastrtps::types::ReturnCode_t;

RobotMap cut_robot_map(const octomap::OcTree& world, const std::string& id, const Eigen::AlignedBox3d& box,
                       const Eigen::Matrix4d& T_robot_world) {
  return RobotMap{id, mapmerge::crop_and_transform(world, box, Eigen::Isometry3d(T_robot_world)), T_robot_world};
}

std::shared_ptr<const octomap::OcTree> load_data_map(const std::string& name) {
  return read_octree_file(std::string(MAPMERGE_DATA_DIR) + "/" + name);
}

std::string data_map_problem(const std::string& name) {
  const std::string path = std::string(MAPMERGE_DATA_DIR) + "/" + name;
  if (std::ifstream(path).good()) return "";
  return "no map " + path + " (give the name of a file in data/, e.g. fr_079.bt)";
}

RobotPublisher::RobotPublisher(int domain, const std::string& id, const wire::ProfileSpec& profile,
                               const wire::SecurityOptions& security)
    : id_(id) {
  wire::ParticipantOptions o;
  o.domain = domain;
  o.profile = profile;
  o.security = security;
  o.name = "robot_" + id;
  participant_ = std::make_unique<wire::FastddsParticipant>(o);
  writer_ = participant_->create_writer(participant_->topic<mapmerge::MapUpdatePubSubType>(wire::map_topic(id)),
                                        wire::TopicKind::State);
}

RobotPublisher::~RobotPublisher() = default;

void RobotPublisher::publish(const octomap::OcTree& tree, const std::string& session, std::uint64_t sequence) {
  publish_bytes(encode_map(tree, Encoding::kOctomapBt), id_, session, sequence);
}

void RobotPublisher::publish_bytes(const std::vector<std::uint8_t>& bytes, const std::string& robot_field,
                                   const std::string& session, std::uint64_t sequence) {
  mapmerge::MapUpdate u;
  u.robot_id(robot_field);
  u.session_id(session);
  u.sequence_number(sequence != 0 ? sequence : ++sequence_);
  u.frame_id(id_ + "/map");
  u.encoding("octomap-bt");
  u.data(bytes);
  writer_->write(&u);
}

RosRobotPublisher::RosRobotPublisher(int domain, const std::string& id) : id_(id) {
  wire::ParticipantOptions o;
  o.domain = domain;
  o.name = "ros_robot_" + id;
  participant_ = std::make_unique<wire::FastddsParticipant>(o);
  writer_ = participant_->create_writer(
      participant_->topic<octomap_msgs::msg::dds_::Octomap_PubSubType>(wire::ros_octomap_topic(id)),
      wire::TopicKind::State);
}

RosRobotPublisher::~RosRobotPublisher() = default;

void RosRobotPublisher::publish(const octomap::OcTree& tree) {
  const auto body = encode_tree_body(tree, true);
  octomap_msgs::msg::dds_::Octomap_ m;
  m.header().frame_id(id_ + "/map");
  m.binary(true);
  m.id("OcTree");
  m.resolution(tree.getResolution());
  m.data(std::vector<int8_t>(body.begin(), body.end()));
  writer_->write(&m);
}

double rotation_error_deg(const Eigen::Matrix4d& T_true, const Eigen::Matrix4d& T_est) {
  const Eigen::Matrix3d dR = T_true.topLeftCorner<3, 3>().transpose() * T_est.topLeftCorner<3, 3>();
  return std::acos(std::clamp((dR.trace() - 1.0) / 2.0, -1.0, 1.0)) * 180.0 / M_PI;
}

double translation_error_m(const Eigen::Matrix4d& T_true, const Eigen::Matrix4d& T_est) {
  return (T_true.topRightCorner<3, 1>() - T_est.topRightCorner<3, 1>()).norm();
}

double global_coverage_after(FleetListener& op, const octomap::OcTree& expected, const Eigen::Matrix4d& T_global_expected,
                             double share, std::chrono::seconds timeout) {
  const auto coverage = [&] {
    const auto g = op.global();
    return g.tree ? occupied_coverage(*g.tree, expected, T_global_expected) : 0.0;
  };
  op.wait_for([&] { return coverage() > share; }, timeout);
  return coverage();
}

double occupied_coverage(const octomap::OcTree& map, const octomap::OcTree& expected,
                         const Eigen::Matrix4d& T_map_expected, int stride) {
  std::size_t seen = 0, hit = 0;
  int i = 0;
  const double r = map.getResolution();
  for (auto it = expected.begin_leafs(), end = expected.end_leafs(); it != end; ++it) {
    if (!expected.isNodeOccupied(*it) || (i++ % stride) != 0) continue;
    const Eigen::Vector4d p = T_map_expected * Eigen::Vector4d(it.getX(), it.getY(), it.getZ(), 1.0);
    ++seen;
    bool found = false;
    for (int dx = -1; dx <= 1 && !found; ++dx)
      for (int dy = -1; dy <= 1 && !found; ++dy)
        for (int dz = -1; dz <= 1 && !found; ++dz) {
          const auto* n = map.search(p.x() + dx * r, p.y() + dy * r, p.z() + dz * r);
          found = n != nullptr && map.isNodeOccupied(n);
        }
    hit += found ? 1 : 0;
  }
  return seen == 0 ? 0.0 : static_cast<double>(hit) / static_cast<double>(seen);
}

std::string temp_dir(const std::string& name) {
  const auto base = std::filesystem::temp_directory_path() / ("mapmerge_server_test_" + std::to_string(::getpid()));
  const auto dir = base / name;
  std::filesystem::remove_all(dir);
  std::filesystem::create_directories(dir);
  return dir.string();
}

}  // namespace mapmerge::test
