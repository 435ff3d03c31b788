#pragma once
/// Conversions between the server's vendor-free messages and the generated Fast DDS types.

#include <string>

#include "mapmerge/server/messages.hpp"
#include "mapmerge_fastdds/mapmerge.h"
#include "mapmerge_fastdds/ros2_msgs.h"

namespace mapmerge::server::convert {

MapSample from_native(const mapmerge::MapUpdate& m, const std::string& topic, const std::string& topic_robot);
MapSample from_ros(const octomap_msgs::msg::dds_::Octomap_& m, const std::string& topic,
                   const std::string& topic_robot, std::uint64_t sequence);

mapmerge::GlobalMap to_native(const GlobalMapOut& g);
/// g's delta (g.delta must hold one).
mapmerge::GlobalMapDelta to_native_delta(const GlobalMapOut& g);
octomap_msgs::msg::dds_::Octomap_ to_ros(const GlobalMapOut& g);
mapmerge::RobotPose to_native(const PoseOut& p, std::uint64_t version, const std::string& global_frame);
geometry_msgs::msg::dds_::TransformStamped_ to_tf(const PoseOut& p, const std::string& global_frame);
mapmerge::ServerStatus to_native(const StatusOut& s);

}  // namespace mapmerge::server::convert
