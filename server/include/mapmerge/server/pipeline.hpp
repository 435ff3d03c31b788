#pragma once
/// What the server does with one robot's turn (run on a scheduler thread), as named stages:
///   ingest (decode -> validate -> prepare -> registry -> store) -> place, where place is
///   reference (defines `global`) | refine (transform known: local only) | search (unknown:
///   global alignment against the aligned robots, largest first).
/// On spare capacity (Scheduler idle work): extra pairs = aligned robots that share no edge but
/// overlap by their pose estimates, refined locally from those estimates (global search as
/// fallback), so the fleet pose graph gets cycles; before those, rescues = a robot still unknown
/// searched for again against a partner that refused it, on denser features (align::rescue). A
/// pair is tried once per pair of maps.

#include <atomic>
#include <cstdint>
#include <deque>
#include <functional>
#include <map>
#include <mutex>
#include <optional>
#include <set>
#include <string>
#include <utility>
#include <vector>

#include <Eigen/Core>

#include "mapmerge/server/config.hpp"
#include "mapmerge/server/messages.hpp"
#include "mapmerge/server/registry.hpp"
#include "mapmerge/server/store.hpp"

namespace mapmerge::server {

struct PipelineCounters {
  std::uint64_t updates_accepted = 0;
  std::uint64_t updates_rejected = 0;
  std::uint64_t merges_run = 0;
  std::uint64_t extra_pairs_tried = 0;   ///< extra pairs aligned (refine, maybe global) [count]
  std::uint64_t extra_edges_added = 0;   ///< of which accepted: edges beyond what placing needed [count]
  std::uint64_t rescues_tried = 0;       ///< rescue searches run (merge.idle_rescue) [count]
  std::uint64_t rescues_accepted = 0;    ///< of which accepted [count]
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
    std::function<void()> more_idle_work;                 ///< extra pairs may have appeared
    /// Run search_job(robot) as a turn of its own (so the robot's next map is checked and stored
    /// while its previous one is searched for); without it the search runs inline.
    std::function<void(const std::string& job)> search;
  };

  /// The scheduler key of `robot`'s refinement turn (ids cannot contain '#').
  static std::string refine_job(const std::string& robot) { return robot + "#refine"; }
  /// The scheduler key of `robot`'s global-search turn.
  static std::string search_job(const std::string& robot) { return robot + "#search"; }
  /// The scheduler key of the turn that lets go of idle alignment data (release_alignment_data).
  static std::string release_job() { return "#release"; }
  /// Whether some robot holds a prepared map or octree no alignment used for
  /// merge.alignment_data_hold_s.
  bool alignment_data_idle() const;

  /// `store` may be null (no persistence).
  Pipeline(const ServerConfig& config, Registry& registry, Store* store, Hooks hooks);

  /// One turn of `robot`: its newest map (if any arrived) and/or a retry; for refine_job(robot),
  /// the local refinement of the robot's latest map; for search_job(robot), the global search of
  /// its latest map (if it is still unknown); for release_job(), lets go of the prepared maps and
  /// octrees no alignment used for merge.alignment_data_hold_s.
  void process(const std::string& robot, std::optional<MapSample> map, bool retry);
  /// Installs a map from the store at start-up (no persistence, no alignment).
  bool restore(const MapSample& map);
  /// Installs the pairs tried before a restart (not tried again while their maps are the same).
  void restore_attempts(const std::vector<PairAttempt>& attempts);
  /// Idle work for the scheduler: a rescue (merge.idle_rescue) if one is due, else the best extra
  /// pair (largest estimated overlap), or an empty function when there is neither. Thread-safe; a
  /// pair is handed out once at a time.
  std::function<void()> next_idle_work();
  /// The extra pair part of next_idle_work() alone.
  std::function<void()> next_extra_pair();
  /// The rescue part of next_idle_work() alone.
  std::function<void()> next_rescue();

  PipelineCounters counters() const;
  std::vector<MergeReportOut> recent_merges() const;

 private:
  bool ingest(const MapSample& map, bool persist);
  /// The robot's map of the same session with the same bytes again: records the new sequence
  /// (store first, then registry) and returns true; nothing is decoded.
  bool unchanged(const MapSample& map);
  /// Stores the edge set with `edge`, then installs `edge` in the registry; false (nothing
  /// installed) when `target` or `source` (the records aligned) is no longer its robot's session.
  bool accept_edge(const Edge& edge, const RobotRecord& target, const RobotRecord& source);
  void warn_on_resolution(const std::string& robot, double resolution) const;
  void place(const std::string& robot);
  /// Refines the robot's own edges; true when a transform moved noticeably.
  bool refine_known(const RobotRecord& robot);
  bool moved_noticeably(const Eigen::Matrix4d& before, const Eigen::Matrix4d& after) const;
  void search_unknown(const RobotRecord& robot);
  /// `robot`'s prepared map; with features (keypoints, descriptors) only when a global search needs
  /// them: a known robot's refinement prepares stages 1-2 only (faster, smaller). The caller holds
  /// a Registry::AlignmentUse of `robot` while it uses the map (which also stamps its last use).
  std::shared_ptr<const align::PreparedMap> prepared(const std::string& robot, bool features);
  void refine_turn(const std::string& robot);
  void search_turn(const std::string& robot);
  void release_turn();
  /// Prepared maps last used before this are idle (merge.alignment_data_hold_s ago).
  Registry::Clock::time_point alignment_data_cutoff() const;
  /// Stores the reference and the registry's edges except those of `robot`.
  void store_edges_without(const std::string& robot);
  /// Asks for a republish and, when `joined` (the aligned group grew), a retry of every
  /// unaligned robot.
  void on_new_alignment(const std::string& robot, bool joined);
  void report(MergeReportOut report);
  void persist_edges();

  /// An extra pair: target (the larger map) <- source, with the pose estimates' T_target_source.
  /// Idle work on a pair: target <- source, as their maps were when it was picked.
  struct PairJob {
    std::string target, source;
    std::uint64_t target_revision = 0, source_revision = 0;
  };
  using RecordPair = std::pair<std::shared_ptr<const RobotRecord>, std::shared_ptr<const RobotRecord>>;
  /// The job's target and source records, if both maps are still the ones it was picked with.
  std::optional<RecordPair> current_records(const PairJob& job) const;
  struct ExtraPair : PairJob {
    std::size_t target_hash = 0, source_hash = 0;
    Eigen::Matrix4d T_target_source = Eigen::Matrix4d::Identity();
    double overlap = 0.0;
  };
  std::optional<ExtraPair> pick_extra_pair();
  double cached_overlap(const RobotRecord& target, const RobotRecord& source, const Eigen::Matrix4d& T_target_source);
  void align_extra_pair(const ExtraPair& pair);
  /// True once the server shuts down (Hooks::cancelled).
  bool stopping() const;
  /// A pair picked for idle work (in in_progress_, where pick_rescue / pick_extra_pair put it):
  /// handed back when the work ends, however it ends.
  class PairClaim {
   public:
    PairClaim(Pipeline& pipeline, std::string a, std::string b)
        : pipeline_(pipeline), a_(std::move(a)), b_(std::move(b)) {}
    ~PairClaim();
    PairClaim(const PairClaim&) = delete;
    PairClaim& operator=(const PairClaim&) = delete;

   private:
    Pipeline& pipeline_;
    std::string a_, b_;
  };
  /// A rescue: `target` (aligned) <- `source` (unknown).
  std::optional<PairJob> pick_rescue();
  void run_rescue(const PairJob& pair);
  /// The try of (a, b) of this kind with both maps as they are now, if one is on record.
  std::optional<PairAttempt> attempt_now(const RobotRecord& a, const RobotRecord& b, const std::string& kind) const;
  /// A try of (a, b) of this kind ("search", "extra", "rescue") with both maps as they are now is on record.
  bool attempted(const RobotRecord& a, const RobotRecord& b, const std::string& kind) const;
  /// Whether a try of this kind between the two robots, with any of their maps, was refused last.
  bool refused_before(const RobotRecord& a, const RobotRecord& b, const std::string& kind) const;
  void record_attempt(const RobotRecord& a, const RobotRecord& b, const std::string& kind, bool accepted,
                      const std::string& reason);

  const ServerConfig& config_;
  Registry& registry_;
  Store* store_;
  Hooks hooks_;
  std::atomic<std::uint64_t> accepted_{0}, rejected_{0}, merges_{0}, extra_tried_{0}, extra_added_{0},
      rescues_tried_{0}, rescues_accepted_{0};
  std::mutex alignment_mutex_;  ///< one edge set written and installed at a time; guards edge_basis_
  /// Per accepted edge (target, source): the node counts of the two maps it was aligned on.
  std::map<std::pair<std::string, std::string>, std::pair<std::size_t, std::size_t>> edge_basis_;
  /// Whether edge (target, source)'s maps changed enough since it was aligned to refine it.
  bool worth_refining(const Edge& edge);
  struct OverlapEstimate {
    std::size_t target_hash = 0, source_hash = 0;
    Eigen::Matrix4d T_target_source = Eigen::Matrix4d::Identity();
    double overlap = 0.0;
  };
  mutable std::mutex pairs_mutex_;  ///< guards the three below
  std::map<std::string, PairAttempt> attempts_;  ///< by "robot_a|robot_b|kind", a < b
  std::set<std::pair<std::string, std::string>> in_progress_;            ///< extra pairs and rescues being aligned
  std::map<std::pair<std::string, std::string>, OverlapEstimate> overlaps_;  ///< by (target, source)
  mutable std::mutex reports_mutex_;
  std::deque<MergeReportOut> reports_;
};

}  // namespace mapmerge::server
