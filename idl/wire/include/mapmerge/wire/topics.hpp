#pragma once
/// Topic names of the mapmerge wire (ROS 2 style: the "rt/" prefix is how ROS 2 maps a topic
/// name to a DDS topic name). Per-robot topics carry the robot id in their name, so DDS
/// Security permissions can restrict each robot to its own topics.

#include <optional>
#include <string>

namespace mapmerge::wire {

/// rt/<robot>/mapmerge/map — mapmerge::MapUpdate, robot -> server.
std::string map_topic(const std::string& robot_id);
/// The robot id of a map_topic() name, or nothing for any other topic.
std::optional<std::string> robot_of_map_topic(const std::string& topic);

/// A ROS 2 octomap_msgs/Octomap topic of a robot from a pattern with "{robot}" in it
/// (default "rt/{robot}/octomap_binary").
std::string ros_octomap_topic(const std::string& robot_id,
                              const std::string& pattern = "rt/{robot}/octomap_binary");
/// The robot id of a topic matching `pattern`, or nothing.
std::optional<std::string> robot_of_ros_octomap_topic(
    const std::string& topic, const std::string& pattern = "rt/{robot}/octomap_binary");

inline constexpr const char* kGlobalMapTopic = "rt/mapmerge/global";      ///< mapmerge::GlobalMap
inline constexpr const char* kGlobalDeltaTopic = "rt/mapmerge/global_delta";  ///< mapmerge::GlobalMapDelta
inline constexpr const char* kPosesTopic = "rt/mapmerge/poses";           ///< mapmerge::RobotPose
inline constexpr const char* kStatusTopic = "rt/mapmerge/status";         ///< mapmerge::ServerStatus
inline constexpr const char* kRequestTopic = "rt/mapmerge/request";       ///< mapmerge::MapRequest
inline constexpr const char* kRosGlobalMapTopic = "rt/mapmerge/global_map";  ///< octomap_msgs/Octomap
inline constexpr const char* kTfTopic = "rt/tf";                          ///< tf2_msgs/TFMessage

/// A robot id is a ROS 2 name token: a letter, then letters, digits or '_', at most 64 chars.
bool is_valid_robot_id(const std::string& robot_id);

}  // namespace mapmerge::wire
