#pragma once
/// The registry: per robot, its latest accepted map, where it came from (session, sequence),
/// its counters, and the accepted pairwise alignments between robots. Thread-safe.

#include <chrono>
#include <cstdint>
#include <map>
#include <memory>
#include <mutex>
#include <set>
#include <string>
#include <utility>
#include <vector>

#include <octomap/OcTree.h>

#include "mapmerge/align/align.hpp"
#include "mapmerge/graph/pose_graph.hpp"
#include "mapmerge/map/held_map.hpp"
#include "mapmerge/server/pose_graph.hpp"

namespace mapmerge::server {

enum class RobotStatus { kUnknown, kAligned, kRejected };
const char* to_string(RobotStatus status);

struct RobotRecord {
  std::string robot_id;
  std::string session_id;            ///< the robot's boot/session; a new one restarts numbering
  std::uint64_t sequence = 0;        ///< sequence number of the map held
  std::string frame_id;              ///< the robot's map frame
  double resolution = 0.0;           ///< [m]
  double received_unix = 0.0;        ///< arrival time of the map held [s since epoch]
  std::shared_ptr<const HeldMap> map;                  ///< null until a map was accepted; its tree
                                                       ///< is built when an alignment needs it
  std::shared_ptr<const align::PreparedMap> prepared;  ///< alignment features of `map`
  std::uint64_t map_revision = 0;    ///< counts accepted maps of this robot (in memory)
  std::size_t content_hash = 0;      ///< hash of the payload bytes of the map held
  std::set<std::string> tried;       ///< robots a global search of this revision already failed against
  std::uint64_t updates_accepted = 0;
  std::uint64_t updates_rejected = 0;
  std::string last_error;            ///< reason of the last rejected update
};

/// Whether an update with (session, sequence) is new for its robot.
enum class Admission {
  kNew,         ///< the next update of the robot's session
  kNewSession,  ///< a new session (a restarted robot): numbering starts again
  kDuplicate,   ///< the update held already (a republish, a client's resend)
  kOutOfOrder,  ///< older than the update held
  kConflict,    ///< a session that another session of the robot replaced, while that one still
                ///< publishes: two participants use one robot id
};
const char* to_string(Admission a);

class Registry {
 public:
  using Clock = std::chrono::steady_clock;
  /// Decides on (and remembers) an incoming update's key; called before any decoding. Within a
  /// session, sequence numbers compare as 64-bit serial numbers (RFC 1982): 0 follows 2^64 - 1.
  /// A new session takes the robot over at once (a restarted robot), unless it is one that an
  /// earlier takeover replaced and the session in force has published within the conflict hold:
  /// then two participants publish as one robot, and the replaced session is refused (kConflict)
  /// until the one in force has been silent for the hold.
  Admission admit(const std::string& robot, const std::string& session, std::uint64_t sequence,
                  Clock::time_point now = Clock::now());
  /// How long the session in force keeps a robot id against a session it replaced [s].
  void set_conflict_hold(double seconds);
  /// Duplicate and out-of-order updates of `robot` ignored so far.
  std::uint64_t ignored(const std::string& robot) const;
  /// The session in force for `robot` (empty before its first update).
  std::string session_of(const std::string& robot) const;
  /// True the first time a conflicting `session` of `robot` is reported (once per takeover).
  bool first_conflict(const std::string& robot, const std::string& session);
  /// The sequence number after the last one admitted for (robot, session); 1 for a new session.
  std::uint64_t next_sequence(const std::string& robot, const std::string& session) const;

  /// Installs an accepted map (record fields other than counters and alignment are replaced).
  void put_map(RobotRecord record);
  /// When the robot's map of the same session has exactly this content already, records the new
  /// (sequence, arrival) without a new revision, so nothing is decoded, prepared or searched
  /// again, and returns true. A robot republishing an unchanged map costs a hash.
  bool touch_if_unchanged(const std::string& robot, const std::string& session, std::uint64_t sequence,
                          std::size_t content_hash, double received_unix);
  /// Counts a rejected update of `robot` with its reason.
  void reject(const std::string& robot, const std::string& reason);
  void set_prepared(const std::string& robot, std::uint64_t revision,
                    std::shared_ptr<const align::PreparedMap> prepared);
  void mark_tried(const std::string& robot, std::uint64_t revision, const std::string& other);
  /// Notes that an alignment uses `robot`'s prepared map at `now`.
  void note_alignment_use(const std::string& robot, Clock::time_point now = Clock::now());
  /// Holds a robot's alignment data while an alignment runs on it: never idle while held (an
  /// alignment may run longer than merge.alignment_data_hold_s), idle time counts from its end.
  class AlignmentUse {
   public:
    AlignmentUse(Registry& registry, std::string robot);
    ~AlignmentUse();
    AlignmentUse(const AlignmentUse&) = delete;
    AlignmentUse& operator=(const AlignmentUse&) = delete;

   private:
    Registry& registry_;
    std::string robot_;
  };
  /// The robots holding a prepared map (or an octree built from their bytes) that no alignment
  /// used since `cutoff`.
  std::vector<std::string> idle_alignment_data(Clock::time_point cutoff) const;
  /// Lets go of those robots' prepared maps and octrees (built again from the maps' bytes when
  /// an alignment needs them; the maps themselves are unchanged); returns the robots released.
  std::vector<std::string> release_alignment_data(Clock::time_point cutoff);

  /// Adds or replaces the edge between target and source.
  void put_edge(const Edge& edge);
  std::vector<Edge> edges() const;
  std::vector<Edge> edges_of(const std::string& robot) const;

  /// The robot defining the global frame; set once (by config, the store, or the first map).
  std::string reference() const;
  /// Sets the reference if none is set yet; returns the reference in force.
  std::string claim_reference(const std::string& robot);

  std::shared_ptr<const RobotRecord> get(const std::string& robot) const;
  std::vector<std::shared_ptr<const RobotRecord>> all() const;
  /// Global poses of the robots connected to the reference that hold a map: the optimised fleet
  /// pose graph (mapmerge::graph; cycle-inconsistent edges left out, a robot whose edges are all
  /// rejected is not connected), or, when the graph has no valid solution, the composed path.
  std::map<std::string, GlobalPose> poses() const;
  /// What the pose graph made of every edge (accepted, rejected with reason and evidence, or
  /// not connected to the reference), sorted by (target, source).
  std::vector<EdgeVerdict> edge_verdicts() const;
  /// The edges the pose graph rejected (inconsistent with the rest of the graph).
  std::vector<EdgeVerdict> rejected_edges() const;
  RobotStatus status(const std::string& robot) const;

  /// Whether a writer of the robot's map topic is matched, and how often it was lost.
  struct Presence {
    bool alive = false;
    std::uint32_t times_lost = 0;
  };
  /// Records that the robot's writers came (alive) or all went; returns false when nothing changed.
  bool set_alive(const std::string& robot, bool alive);
  Presence presence(const std::string& robot) const;

 private:
  struct Seen {
    std::string session;               ///< the session in force
    std::uint64_t sequence = 0;        ///< its last admitted sequence
    Clock::time_point last{};          ///< when it last published (new, repeated or older update)
    std::vector<std::string> replaced; ///< sessions it (or an earlier one) took the robot over from
    std::set<std::string> warned;      ///< replaced sessions reported as conflicting already
    std::uint64_t ignored = 0;         ///< duplicates and out-of-order updates
  };
  RobotRecord& mutable_record(const std::string& robot);
  bool alignment_data_idle_locked(const std::string& robot, const RobotRecord& rec, Clock::time_point cutoff) const;
  std::map<std::string, GlobalPose> poses_locked() const;
  std::map<std::string, GlobalPose> composed_poses_locked() const;
  graph::GraphSolution solve_locked() const;

  mutable std::mutex mutex_;
  std::map<std::string, Seen> seen_;
  double conflict_hold_s_ = 30.0;
  std::map<std::string, Presence> presence_;
  std::map<std::string, Clock::time_point> alignment_use_;  ///< last use of a robot's prepared map
  std::map<std::string, int> alignment_holds_;             ///< alignments running on a robot's data
  std::map<std::string, std::shared_ptr<RobotRecord>> records_;
  std::map<std::pair<std::string, std::string>, Edge> edges_;
  std::string reference_;
  // The fleet pose graph: one per registry (so per server), guarded by mutex_; rebuilt from
  // edges_ when they changed, optimised incrementally (a cached solution when nothing changed).
  mutable graph::PoseGraph graph_;
  mutable bool graph_stale_ = true;
  graph::GraphConfig graph_config_;
};

}  // namespace mapmerge::server
