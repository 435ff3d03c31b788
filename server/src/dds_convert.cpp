#include "dds_convert.hpp"

#include <chrono>
#include <cmath>

#include <Eigen/Geometry>

namespace mapmerge::server {

double unix_now() {
  return std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
}

namespace convert {
namespace {

template <class Time>
Time make_time(double unix_s) {
  Time t;
  const double sec = std::floor(unix_s);
  t.sec(static_cast<int32_t>(sec));
  t.nanosec(static_cast<uint32_t>((unix_s - sec) * 1e9));
  return t;
}

mapmerge::PoseStatus to_native(PoseState s) {
  switch (s) {
    case PoseState::kAligned: return mapmerge::POSE_ALIGNED;
    case PoseState::kRejected: return mapmerge::POSE_REJECTED;
    case PoseState::kUnknown: break;
  }
  return mapmerge::POSE_UNKNOWN;
}

}  // namespace

MapSample from_native(const mapmerge::MapUpdate& m, const std::string& topic, const std::string& topic_robot) {
  MapSample s;
  s.robot_id = m.robot_id();
  s.topic_robot = topic_robot;
  s.topic = topic;
  s.session_id = m.session_id();
  s.sequence = m.sequence_number();
  s.frame_id = m.frame_id();
  s.resolution = m.resolution();
  s.encoding = m.encoding();
  s.data = m.data();
  s.received_unix = unix_now();
  return s;
}

MapSample from_ros(const octomap_msgs::msg::dds_::Octomap_& m, const std::string& topic,
                   const std::string& topic_robot, std::uint64_t sequence) {
  MapSample s;
  s.robot_id = s.topic_robot = topic_robot;
  s.topic = topic;
  s.session_id = "ros2";
  s.sequence = sequence;
  s.frame_id = m.header().frame_id();
  s.resolution = m.resolution();
  s.ros = true;
  s.ros_binary = m.binary();
  s.ros_id = m.id();
  s.data.assign(m.data().begin(), m.data().end());
  s.received_unix = unix_now();
  return s;
}

namespace {
std::vector<mapmerge::MapContribution> to_native(const std::vector<Contribution>& contributors) {
  std::vector<mapmerge::MapContribution> out;
  for (const Contribution& c : contributors) {
    mapmerge::MapContribution mc;
    mc.robot_id(c.robot_id);
    mc.session_id(c.session_id);
    mc.sequence_number(c.sequence);
    out.push_back(std::move(mc));
  }
  return out;
}
}  // namespace

mapmerge::GlobalMap to_native(const GlobalMapOut& g) {
  mapmerge::GlobalMap m;
  m.version(g.version);
  m.stamp(make_time<mapmerge::Time>(g.stamp_unix));
  m.frame_id(g.frame_id);
  m.resolution(g.resolution);
  m.encoding(g.encoding);
  m.data(g.data);
  m.contributors(to_native(g.contributors));
  return m;
}

mapmerge::GlobalMapDelta to_native_delta(const GlobalMapOut& g) {
  mapmerge::GlobalMapDelta m;
  m.version(g.version);
  m.base_version(g.delta->base_version);
  m.base_hash(g.delta->base_hash);
  m.hash(g.hash);
  m.stamp(make_time<mapmerge::Time>(g.stamp_unix));
  m.frame_id(g.frame_id);
  m.resolution(g.resolution);
  m.blocks().reserve(g.delta->blocks.size());
  for (const BlockPatch& p : g.delta->blocks) {
    mapmerge::MapBlock b;
    b.block(p.block);
    b.state(static_cast<std::uint8_t>(p.state));
    b.records(p.records);
    m.blocks().push_back(std::move(b));
  }
  m.contributors(to_native(g.contributors));
  return m;
}

octomap_msgs::msg::dds_::Octomap_ to_ros(const GlobalMapOut& g) {
  octomap_msgs::msg::dds_::Octomap_ m;
  m.header().stamp(make_time<builtin_interfaces::msg::dds_::Time_>(g.stamp_unix));
  m.header().frame_id(g.frame_id);
  m.binary(true);
  m.id("OcTree");
  m.resolution(g.resolution);
  m.data(std::vector<int8_t>(g.ros_body.begin(), g.ros_body.end()));
  return m;
}

mapmerge::RobotPose to_native(const PoseOut& p, std::uint64_t version, const std::string& global_frame) {
  mapmerge::RobotPose m;
  m.robot_id(p.robot_id);
  m.stamp(make_time<mapmerge::Time>(unix_now()));
  m.global_frame_id(global_frame);
  m.robot_frame_id(p.robot_frame);
  const Eigen::Quaterniond q(Eigen::Matrix3d(p.T_global_robot.topLeftCorner<3, 3>()));
  m.T_global_robot().translation({p.T_global_robot(0, 3), p.T_global_robot(1, 3), p.T_global_robot(2, 3)});
  m.T_global_robot().rotation({q.x(), q.y(), q.z(), q.w()});
  m.fitness(p.fitness);
  m.quality(p.quality);
  m.status(to_native(p.state));
  m.global_version(version);
  return m;
}

geometry_msgs::msg::dds_::TransformStamped_ to_tf(const PoseOut& p, const std::string& global_frame) {
  geometry_msgs::msg::dds_::TransformStamped_ t;
  t.header().stamp(make_time<builtin_interfaces::msg::dds_::Time_>(unix_now()));
  t.header().frame_id(global_frame);
  t.child_frame_id(p.robot_frame);
  const Eigen::Quaterniond q(Eigen::Matrix3d(p.T_global_robot.topLeftCorner<3, 3>()));
  t.transform().translation().x(p.T_global_robot(0, 3));
  t.transform().translation().y(p.T_global_robot(1, 3));
  t.transform().translation().z(p.T_global_robot(2, 3));
  t.transform().rotation().x(q.x());
  t.transform().rotation().y(q.y());
  t.transform().rotation().z(q.z());
  t.transform().rotation().w(q.w());
  return t;
}

mapmerge::ServerStatus to_native(const StatusOut& s) {
  mapmerge::ServerStatus m;
  m.stamp(make_time<mapmerge::Time>(unix_now()));
  m.global_version(s.global_version);
  for (const RobotStateOut& r : s.robots) {
    mapmerge::RobotState rs;
    rs.robot_id(r.robot_id);
    rs.status(to_native(r.state));
    rs.session_id(r.session_id);
    rs.sequence_number(r.sequence);
    rs.resolution(r.resolution);
    rs.updates_accepted(r.accepted);
    rs.updates_rejected(r.rejected);
    rs.updates_ignored(r.ignored);
    rs.last_error(r.last_error);
    rs.alive(r.alive);
    rs.times_lost(r.times_lost);
    m.robots().push_back(rs);
  }
  for (const MergeReportOut& r : s.recent_merges) {
    mapmerge::MergeReport mr;
    mr.target_robot(r.target);
    mr.source_robot(r.source);
    mr.accepted(r.accepted);
    mr.global_search(r.global_search);
    mr.fitness(std::isfinite(r.fitness) ? r.fitness : -1.0);
    mr.duration_s(r.duration_s);
    mr.detail(r.detail);
    mr.stamp(make_time<mapmerge::Time>(r.stamp_unix));
    m.recent_merges().push_back(mr);
  }
  m.updates_received(s.updates_received);
  m.updates_rejected(s.updates_rejected);
  m.updates_ignored(s.updates_ignored);
  m.merges_run(s.merges_run);
  m.merges_coalesced(s.merges_coalesced);
  m.store_ok(s.store_ok);
  m.store_error(s.store_error);
  m.store_failures(s.store_failures);
  m.store_pending(s.store_pending);
  m.merges_queued(s.merges_queued);
  m.merges_queued_max(s.merges_queued_max);
  m.merges_running(s.merges_running);
  return m;
}

}  // namespace convert
}  // namespace mapmerge::server
