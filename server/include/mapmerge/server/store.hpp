#pragma once
/// Persistence of the registry in SQLite (state.sqlite in the state directory, WAL mode): robot
/// maps as received, accepted alignments with their quality and the pose graph's verdict, pairs
/// tried, the reference, the last global map and its poses.
/// Every save is one transaction, so a kill at any moment loses at most the save under way.
///
/// A write that fails (disk full, file size limit, read-only directory, I/O error) loses
/// nothing in memory: the store keeps the latest unwritten map of each robot, alignment and
/// global map (newer ones replace older), reports itself unhealthy, and retry() writes them
/// when the disk works again. A failed transaction is rolled back: the file stays consistent.

#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

#include "mapmerge/server/config.hpp"
#include "mapmerge/server/messages.hpp"
#include "mapmerge/server/pose_graph.hpp"

struct sqlite3;

namespace mapmerge::server {

class StoreError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

/// Everything a restarted server needs.
struct StoreSnapshot {
  std::string reference;
  std::vector<MapSample> maps;         ///< each robot's latest accepted map, as received
  std::vector<Edge> edges;             ///< with their quality and information matrix
  std::vector<EdgeVerdict> verdicts;   ///< the pose graph's verdict on each edge when last saved
  std::vector<PairAttempt> attempts;   ///< pairs tried, per pair the last try
  std::optional<GlobalMapOut> global;  ///< the last published global map
  std::vector<PoseOut> poses;          ///< the poses published with it
};

/// Whether the store keeps up (published on the status topic).
struct StoreHealth {
  bool ok = true;                ///< the last write succeeded
  std::string error;             ///< reason of the last failure while not ok
  std::uint64_t failures = 0;    ///< failed writes since start
  std::uint64_t pending = 0;     ///< writes held in memory for retry()
};

class Store {
 public:
  /// Opens (creating if needed) <state_dir>/state.sqlite. Throws StoreError.
  explicit Store(const StoreConfig& config);
  ~Store();
  Store(const Store&) = delete;
  Store& operator=(const Store&) = delete;

  // Each save returns false when the write failed; the data is then pending (see above).
  bool save_map(const MapSample& map);
  /// Records a new (sequence, arrival) of the robot's map held, whose bytes did not change.
  bool touch_map(const std::string& robot, const std::string& session, std::uint64_t sequence, double received_unix);
  /// The reference and every edge (quality, information, the graph's verdict), replacing the
  /// stored ones: one transaction.
  bool save_alignment(const std::string& reference, const std::vector<Edge>& edges,
                      const std::vector<EdgeVerdict>& verdicts = {});
  /// Records a try of a pair (replacing the pair's previous one). Throws StoreError.
  void save_attempt(const PairAttempt& attempt);
  bool save_global(const GlobalMapOut& global, const std::vector<PoseOut>& poses);
  /// Writes what is pending; true when nothing is left.
  bool retry();
  /// Copies the write-ahead log into the database file (SQLite's passive checkpoint: never waits
  /// for readers). Call it off the update path (the server does, every status period); the
  /// store checkpoints by itself only once the log reaches 64 MB. Crash safety is the same
  /// either way: a log not yet copied is replayed when the store is opened.
  struct Checkpoint {
    bool ok = false;
    std::size_t wal_frames = 0;           ///< pages in the log
    std::size_t checkpointed_frames = 0;  ///< of them, in the database now
  };
  Checkpoint checkpoint();
  StoreHealth health() const;
  StoreSnapshot load();
  std::string path() const { return path_; }

 private:
  struct PendingAlignment {
    std::string reference;
    std::vector<Edge> edges;
    std::vector<EdgeVerdict> verdicts;
  };
  struct Pending {
    std::map<std::string, MapSample> maps;  ///< robot -> latest unwritten map
    std::optional<PendingAlignment> alignment;
    std::optional<std::pair<GlobalMapOut, std::vector<PoseOut>>> global;
    std::size_t size() const { return maps.size() + (alignment ? 1 : 0) + (global ? 1 : 0); }
  };
  void exec(const char* sql);
  void migrate();
  /// Opens the store for writing (WAL, schema, migration); throws StoreError.
  void open_writable();
  /// Opens what is stored read-only (a read-only state directory); db_ stays null if it cannot.
  void open_read_only();
  void close();
  /// Reopens for writing after open_read_only; throws StoreError while that still fails.
  void ensure_writable();
  void transaction(const std::function<void()>& body);
  void write_map(const MapSample& m);
  void write_alignment(const std::string& reference, const std::vector<Edge>& edges,
                       const std::vector<EdgeVerdict>& verdicts);
  void write_global(const GlobalMapOut& g, const std::vector<PoseOut>& poses);
  /// Runs `write`; on failure records it (logged, counted) and returns false.
  bool attempt(const std::string& what, const std::function<void()>& write);
  /// Healthy again once nothing is pending (logged once).
  void settle();

  std::string path_;
  bool synchronous_full_ = true;
  sqlite3* db_ = nullptr;
  bool writable_ = false;  ///< db_ was opened for writing (else read-only or null)
  mutable std::recursive_mutex mutex_;  ///< one transaction at a time on the one connection; guards the rest
  Pending pending_;
  StoreHealth health_;
};

}  // namespace mapmerge::server
