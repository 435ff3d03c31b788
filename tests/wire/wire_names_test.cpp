#include <gtest/gtest.h>

#include "mapmerge/wire/profile.hpp"
#include "mapmerge/wire/topics.hpp"

namespace mapmerge::wire {

TEST(WireNames, MapTopicCarriesTheRobotId) {
  EXPECT_EQ(map_topic("r1"), "rt/r1/mapmerge/map");
  EXPECT_EQ(robot_of_map_topic("rt/r1/mapmerge/map").value(), "r1");
  EXPECT_EQ(robot_of_map_topic("rt/husky_2/mapmerge/map").value(), "husky_2");
  EXPECT_FALSE(robot_of_map_topic("rt/mapmerge/global").has_value());
  EXPECT_FALSE(robot_of_map_topic("rt//mapmerge/map").has_value());
  EXPECT_FALSE(robot_of_map_topic("rt/a/b/mapmerge/map").has_value());
}

TEST(WireNames, RosOctomapTopicFollowsThePattern) {
  EXPECT_EQ(ros_octomap_topic("r2"), "rt/r2/octomap_binary");
  EXPECT_EQ(robot_of_ros_octomap_topic("rt/r2/octomap_binary").value(), "r2");
  EXPECT_EQ(robot_of_ros_octomap_topic("rt/fleet/r3/map", "rt/fleet/{robot}/map").value(), "r3");
  EXPECT_FALSE(robot_of_ros_octomap_topic("rt/tf").has_value());
}

TEST(WireNames, RobotIdsAreRosNameTokens) {
  EXPECT_TRUE(is_valid_robot_id("r1"));
  EXPECT_TRUE(is_valid_robot_id("Husky_07"));
  EXPECT_FALSE(is_valid_robot_id(""));
  EXPECT_FALSE(is_valid_robot_id("1robot"));
  EXPECT_FALSE(is_valid_robot_id("r/1"));
  EXPECT_FALSE(is_valid_robot_id("r 1"));
  EXPECT_FALSE(is_valid_robot_id(std::string(65, 'a')));
}

TEST(WireNames, ProfilesParse) {
  EXPECT_EQ(ProfileSpec::parse("local").kind, ProfileSpec::Kind::Local);
  EXPECT_EQ(ProfileSpec::parse("default").kind, ProfileSpec::Kind::Default);
  EXPECT_THROW(ProfileSpec::parse("loopback"), std::invalid_argument);
  EXPECT_THROW(ProfileSpec::parse("/nonexistent/profile.xml"), std::invalid_argument);
}

}  // namespace mapmerge::wire
