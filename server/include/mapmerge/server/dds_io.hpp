#pragma once
/// The server's DDS side (Fast DDS): discovers robots' map topics as they appear (native
/// rt/<robot>/mapmerge/map and ROS 2 octomap topics by pattern), reads them, answers map
/// requests, and publishes the global map, poses, tf and status. No merge logic here.

#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "mapmerge/server/config.hpp"
#include "mapmerge/server/messages.hpp"

namespace mapmerge::server {

class DdsIo {
 public:
  struct Callbacks {
    std::function<void(MapSample)> on_map;                       ///< a robot map arrived
    std::function<void(const std::string& requester)> on_request;  ///< someone asked for a republish
    std::function<void()> on_discovery;                          ///< a robot topic appeared: call service()
    /// The robot's first map writer matched (true), or its last one went (false: it left, or its
    /// participant's lease expired). Works alike for every vendor's robots (DDS discovery).
    std::function<void(const std::string& robot, bool alive)> on_presence;
  };

  /// Creates the participant and the server's writers/readers. Throws wire::DdsError.
  DdsIo(const NetworkConfig& config, Callbacks callbacks);
  ~DdsIo();
  DdsIo(const DdsIo&) = delete;
  DdsIo& operator=(const DdsIo&) = delete;

  /// Subscribes to robot topics discovered since the last call; returns their names.
  std::vector<std::string> service();

  void publish_global(const GlobalMapOut& global);
  /// The change to the previous version (global.delta), if it holds one: receivers holding that
  /// version patch it (write it before the map itself, which they then need not decode).
  void publish_delta(const GlobalMapOut& global);
  /// Native poses (one sample per robot) and, for aligned robots, tf global -> <robot frame>.
  void publish_poses(const std::vector<PoseOut>& poses, std::uint64_t version, const std::string& global_frame);
  void publish_status(const StatusOut& status);

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace mapmerge::server
