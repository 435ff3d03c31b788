#pragma once
/// What the server does with one robot's turn (run on a scheduler thread), as named stages:
///   ingest (decode -> validate -> prepare -> registry -> store) -> place, where place is
///   reference (defines `global`) | refine (transform known: local only) | search (unknown:
///   global alignment against the aligned robots, largest first).

#include <atomic>
#include <cstdint>
#include <deque>
#include <functional>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

#include "mapmerge/server/config.hpp"
#include "mapmerge/server/messages.hpp"
#include "mapmerge/server/registry.hpp"
#include "mapmerge/server/store.hpp"

namespace mapmerge::server {

struct PipelineCounters {
  std::uint64_t updates_accepted = 0;
  std::uint64_t updates_rejected = 0;
  std::uint64_t merges_run = 0;
};

class Pipeline {
 public:
  struct Hooks {
    std::function<void(const std::string& robot)> retry;  ///< ask for another turn of a robot
    std::function<void()> changed;                        ///< maps or poses changed: republish
    std::function<bool()> cancelled;                      ///< true once the server shuts down
    /// Run refine_job(robot) as a turn of its own (so a known robot's next map is fused while its
    /// previous one is refined); without it the refinement runs inline.
    std::function<void(const std::string& job)> refine;
  };

  /// The scheduler key of `robot`'s refinement turn (ids cannot contain '#').
  static std::string refine_job(const std::string& robot) { return robot + "#refine"; }

  /// `store` may be null (no persistence).
  Pipeline(const ServerConfig& config, Registry& registry, Store* store, Hooks hooks);

  /// One turn of `robot`: its newest map (if any arrived) and/or a retry; for refine_job(robot),
  /// the local refinement of the robot's latest map.
  void process(const std::string& robot, std::optional<MapSample> map, bool retry);
  /// Installs a map from the store at start-up (no persistence, no alignment).
  bool restore(const MapSample& map);

  PipelineCounters counters() const;
  std::vector<MergeReportOut> recent_merges() const;

 private:
  bool ingest(const MapSample& map, bool persist);
  void warn_on_resolution(const std::string& robot, double resolution) const;
  void place(const std::string& robot);
  /// Refines the robot's own edges; true when a transform moved noticeably.
  bool refine_known(const RobotRecord& robot);
  bool moved_noticeably(const Eigen::Matrix4d& before, const Eigen::Matrix4d& after) const;
  void search_unknown(const RobotRecord& robot);
  /// `robot`'s prepared map; with features (keypoints, descriptors) only when a global search needs
  /// them: a known robot's refinement prepares stages 1-2 only (faster, smaller).
  std::shared_ptr<const align::PreparedMap> prepared(const std::string& robot, bool features);
  void refine_turn(const std::string& robot);
  /// Persists alignments, asks for a republish and, when `joined` (the aligned group grew),
  /// a retry of every unaligned robot.
  void on_new_alignment(const std::string& robot, bool joined);
  void report(MergeReportOut report);

  const ServerConfig& config_;
  Registry& registry_;
  Store* store_;
  Hooks hooks_;
  std::atomic<std::uint64_t> accepted_{0}, rejected_{0}, merges_{0};
  mutable std::mutex reports_mutex_;
  std::deque<MergeReportOut> reports_;
};

}  // namespace mapmerge::server
