#include "mapmerge/wire/topics.hpp"

#include <cctype>

namespace mapmerge::wire {
namespace {

constexpr const char* kRobotPlaceholder = "{robot}";

std::optional<std::string> match_pattern(const std::string& topic, const std::string& pattern) {
  const auto at = pattern.find(kRobotPlaceholder);
  if (at == std::string::npos) return std::nullopt;
  const std::string prefix = pattern.substr(0, at);
  const std::string suffix = pattern.substr(at + std::string(kRobotPlaceholder).size());
  if (topic.size() <= prefix.size() + suffix.size()) return std::nullopt;
  if (topic.compare(0, prefix.size(), prefix) != 0) return std::nullopt;
  if (topic.compare(topic.size() - suffix.size(), suffix.size(), suffix) != 0) return std::nullopt;
  std::string robot = topic.substr(prefix.size(), topic.size() - prefix.size() - suffix.size());
  if (!is_valid_robot_id(robot)) return std::nullopt;
  return robot;
}

std::string fill_pattern(const std::string& pattern, const std::string& robot_id) {
  std::string out = pattern;
  const auto at = out.find(kRobotPlaceholder);
  if (at != std::string::npos) out.replace(at, std::string(kRobotPlaceholder).size(), robot_id);
  return out;
}

constexpr const char* kMapPattern = "rt/{robot}/mapmerge/map";

}  // namespace

std::string map_topic(const std::string& robot_id) { return fill_pattern(kMapPattern, robot_id); }

std::optional<std::string> robot_of_map_topic(const std::string& topic) {
  return match_pattern(topic, kMapPattern);
}

std::string ros_octomap_topic(const std::string& robot_id, const std::string& pattern) {
  return fill_pattern(pattern, robot_id);
}

std::optional<std::string> robot_of_ros_octomap_topic(const std::string& topic,
                                                      const std::string& pattern) {
  return match_pattern(topic, pattern);
}

bool is_valid_robot_id(const std::string& robot_id) {
  if (robot_id.empty() || robot_id.size() > 64) return false;
  if (!std::isalpha(static_cast<unsigned char>(robot_id[0]))) return false;
  for (const char c : robot_id) {
    if (!std::isalnum(static_cast<unsigned char>(c)) && c != '_') return false;
  }
  return true;
}

}  // namespace mapmerge::wire
