#pragma once
/// Persistence of the registry in SQLite (state.sqlite in the state directory, WAL mode): robot
/// maps as received, accepted alignments with their quality and the pose graph's verdict, pairs
/// tried, the reference, the last global map and its poses.
/// Every save is one transaction, so a kill at any moment loses at most the save under way.

#include <functional>
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

class Store {
 public:
  /// Opens (creating if needed) <state_dir>/state.sqlite. Throws StoreError.
  explicit Store(const StoreConfig& config);
  ~Store();
  Store(const Store&) = delete;
  Store& operator=(const Store&) = delete;

  void save_map(const MapSample& map);
  /// The reference and every edge (quality, information, the graph's verdict), replacing the
  /// stored ones: one transaction.
  void save_alignment(const std::string& reference, const std::vector<Edge>& edges,
                      const std::vector<EdgeVerdict>& verdicts = {});
  /// Records a try of a pair (replacing the pair's previous one).
  void save_attempt(const PairAttempt& attempt);
  void save_global(const GlobalMapOut& global, const std::vector<PoseOut>& poses);
  StoreSnapshot load();
  std::string path() const { return path_; }

 private:
  void exec(const char* sql);
  void migrate();
  void transaction(const std::function<void()>& body);

  std::string path_;
  sqlite3* db_ = nullptr;
  std::recursive_mutex mutex_;  ///< one transaction at a time on the one connection
};

}  // namespace mapmerge::server
