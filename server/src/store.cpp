#include "mapmerge/server/store.hpp"

#include <algorithm>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <map>
#include <optional>
#include <set>
#include <string_view>
#include <utility>

#include <nlohmann/json.hpp>
#include <spdlog/spdlog.h>

#include "sqlite_stmt.hpp"

namespace mapmerge::server {
namespace {

using detail::Stmt;

constexpr const char* kSchema = R"SQL(
CREATE TABLE IF NOT EXISTS meta(key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS robots(robot_id TEXT PRIMARY KEY, session_id TEXT, sequence INTEGER,
  frame_id TEXT, resolution REAL, received REAL, encoding TEXT, ros INTEGER, ros_binary INTEGER,
  ros_id TEXT, data BLOB NOT NULL);
CREATE TABLE IF NOT EXISTS edges(target TEXT, source TEXT, T BLOB NOT NULL, fitness REAL,
  PRIMARY KEY(target, source));
CREATE TABLE IF NOT EXISTS pair_attempts(robot_a TEXT, robot_b TEXT, kind TEXT, hash_a INTEGER,
  hash_b INTEGER, accepted INTEGER, reason TEXT, stamp REAL, PRIMARY KEY(robot_a, robot_b, kind));
CREATE TABLE IF NOT EXISTS global_map(id INTEGER PRIMARY KEY CHECK(id = 1), version INTEGER,
  stamp REAL, frame_id TEXT, resolution REAL, encoding TEXT, data BLOB, ros_body BLOB,
  contributors TEXT);
CREATE TABLE IF NOT EXISTS poses(robot_id TEXT PRIMARY KEY, frame TEXT, T BLOB NOT NULL,
  fitness REAL, quality REAL, state INTEGER);
)SQL";

/// Columns added to `edges` after its first version (ALTER TABLE on older stores).
constexpr std::pair<const char*, const char*> kEdgeColumns[] = {
    {"inliers", "INTEGER DEFAULT 0"}, {"overlap", "REAL DEFAULT 0"}, {"pivot", "BLOB"},
    {"information", "BLOB"},          {"state", "TEXT"},             {"reason", "TEXT"},
    {"evidence", "TEXT"}};

std::vector<double> to_vec(const Eigen::Matrix4d& T) { return {T.data(), T.data() + 16}; }

template <class M>
void bind_matrix(Stmt& s, int i, const M& m) {
  s.bind(i, m.data(), static_cast<std::size_t>(m.size()) * sizeof(double));
}

/// A matrix from its blob; `fallback` when the blob is missing or has the wrong size.
template <class M>
M matrix_from_blob(const std::vector<std::uint8_t>& b, const M& fallback) {
  M m = fallback;
  if (b.size() == static_cast<std::size_t>(m.size()) * sizeof(double)) std::memcpy(m.data(), b.data(), b.size());
  return m;
}

Eigen::Matrix4d from_blob(const std::vector<std::uint8_t>& b) {
  Eigen::Matrix4d T = Eigen::Matrix4d::Identity();
  if (b.size() == 16 * sizeof(double)) std::memcpy(T.data(), b.data(), b.size());
  return T;
}

std::string contributors_json(const std::vector<Contribution>& cs) {
  nlohmann::json j = nlohmann::json::array();
  for (const auto& c : cs) j.push_back({{"robot", c.robot_id}, {"session", c.session_id}, {"seq", c.sequence}});
  return j.dump();
}

std::vector<Contribution> contributors_from(const std::string& text) {
  std::vector<Contribution> out;
  const auto j = nlohmann::json::parse(text, nullptr, false);
  if (!j.is_array()) return out;
  for (const auto& c : j) out.push_back({c.value("robot", ""), c.value("session", ""), c.value("seq", 0ULL)});
  return out;
}

}  // namespace

Store::Store(const StoreConfig& config) : synchronous_full_(config.synchronous_full) {
  std::error_code ec;
  std::filesystem::create_directories(config.state_dir, ec);
  path_ = (std::filesystem::path(config.state_dir) / "state.sqlite").string();
  if (!std::filesystem::is_directory(config.state_dir)) {  // a wrong path, not a failing disk
    throw StoreError("state directory '" + config.state_dir + "' does not exist and cannot be created" +
                     (ec ? ": " + ec.message() : std::string()));
  }
  try {
    open_writable();
  } catch (const StoreError& e) {
    // A read-only or full state directory: what is stored is restored read-only, the server
    // serves from memory, and every write is kept pending and retried (reopening the store).
    ++health_.failures;
    health_.ok = false;
    health_.error = e.what();
    spdlog::error("state store: {}; serving from memory, new state kept in memory until the store can be "
                  "written", e.what());
    open_read_only();
  }
}

void Store::open_writable() {
  close();
  if (sqlite3_open_v2(path_.c_str(), &db_, SQLITE_OPEN_READWRITE | SQLITE_OPEN_CREATE, nullptr) != SQLITE_OK) {
    const std::string msg = db_ ? sqlite3_errmsg(db_) : "out of memory";
    close();
    throw StoreError("cannot open state store '" + path_ + "': " + msg);
  }
  if (sqlite3_db_readonly(db_, "main") == 1) {  // SQLite falls back to reading a file it cannot write
    close();
    throw StoreError("state store '" + path_ + "' cannot be written (read-only file or file system)");
  }
  try {
    sqlite3_busy_timeout(db_, 5000);
    exec("PRAGMA journal_mode=WAL;");
    exec(synchronous_full_ ? "PRAGMA synchronous=FULL;" : "PRAGMA synchronous=NORMAL;");
    // Checkpoints (copying the WAL into the database, with an fsync) run from checkpoint(),
    // off the update path; SQLite's own after a commit only as a backstop (64 MB of WAL): at its
    // default of 1000 pages one ran every ~2 updates of Freiburg-size maps, adding ~20 ms to them.
    exec("PRAGMA wal_autocheckpoint=16384;");
    exec(kSchema);
    migrate();
  } catch (const StoreError&) {
    close();
    throw;
  }
  writable_ = true;
}

void Store::open_read_only() {
  close();
  if (!std::filesystem::exists(path_)) return;  // nothing stored yet: nothing to restore
  // A WAL store in a directory that cannot be written: readable as is while its -shm exists
  // (a killed server leaves it), else only as an immutable file (a cleanly closed store has
  // nothing in its WAL).
  const bool shm = std::filesystem::exists(path_ + "-shm");
  std::string uri = "file:";
  for (const char c : path_) {
    if (c == '%' || c == '?' || c == '#') {
      char hex[4];
      std::snprintf(hex, sizeof hex, "%%%02X", static_cast<unsigned char>(c));
      uri += hex;
    } else {
      uri += c;
    }
  }
  if (!shm) uri += "?immutable=1";
  try {
    if (sqlite3_open_v2(uri.c_str(), &db_, SQLITE_OPEN_READONLY | SQLITE_OPEN_URI, nullptr) != SQLITE_OK) {
      throw StoreError(db_ ? sqlite3_errmsg(db_) : "out of memory");
    }
    sqlite3_busy_timeout(db_, 5000);
    std::set<std::string> have;
    for (Stmt s(db_, "PRAGMA table_info(edges)"); s.step();) have.insert(s.text(1));
    for (const auto& column : kEdgeColumns) {
      if (have.count(column.first) == 0) throw StoreError("an older schema (no edges." + std::string(column.first) + ")");
    }
    spdlog::warn("state store: '{}' opened read-only: its state is restored, nothing new is written", path_);
  } catch (const StoreError& e) {
    spdlog::error("state store: '{}' cannot be read either ({}): starting empty", path_, e.what());
    close();
  }
}

void Store::close() {
  sqlite3_close(db_);
  db_ = nullptr;
  writable_ = false;
}

void Store::ensure_writable() {
  if (!writable_) open_writable();  // throws StoreError while it still cannot be written
}

void Store::migrate() {
  std::set<std::string> have;
  for (Stmt s(db_, "PRAGMA table_info(edges)"); s.step();) have.insert(s.text(1));
  for (const auto& [name, type] : kEdgeColumns) {
    if (have.count(name) != 0) continue;
    const std::string sql = std::string("ALTER TABLE edges ADD COLUMN ") + name + " " + type + ";";
    exec(sql.c_str());
  }
}

Store::~Store() { close(); }

void Store::exec(const char* sql) {
  char* err = nullptr;
  if (sqlite3_exec(db_, sql, nullptr, nullptr, &err) != SQLITE_OK) {
    const std::string msg = err ? err : "?";
    sqlite3_free(err);
    throw StoreError("sqlite (" + path_ + "): " + msg);
  }
}

void Store::transaction(const std::function<void()>& body) {
  std::lock_guard<std::recursive_mutex> lock(mutex_);
  exec("BEGIN IMMEDIATE;");
  try {
    body();
    exec("COMMIT;");
  } catch (...) {
    sqlite3_exec(db_, "ROLLBACK;", nullptr, nullptr, nullptr);
    throw;
  }
}

bool Store::attempt(const std::string& what, const std::function<void()>& write) {
  try {
    spdlog::debug("state store: writing {}", what);
    ensure_writable();
    write();
    settle();
    spdlog::debug("state store: wrote {}", what);
    return true;
  } catch (const StoreError& e) {
    ++health_.failures;
    health_.ok = false;
    health_.error = e.what();
    spdlog::error("state store: {} not written, kept in memory until the store works again: {}", what, e.what());
    return false;
  }
}

bool Store::save_map(const MapSample& m) {
  std::lock_guard<std::recursive_mutex> lock(mutex_);
  pending_.maps.erase(m.robot_id);  // superseded
  if (attempt("map of robot " + m.robot_id, [&] { write_map(m); })) return true;
  pending_.maps[m.robot_id] = m;
  health_.pending = pending_.size();
  return false;
}

bool Store::touch_map(const std::string& robot, const std::string& session, std::uint64_t sequence,
                      double received_unix) {
  std::lock_guard<std::recursive_mutex> lock(mutex_);
  if (auto it = pending_.maps.find(robot); it != pending_.maps.end()) {  // its bytes are not written yet
    it->second.sequence = sequence;
    it->second.received_unix = received_unix;
    return false;
  }
  return attempt("sequence of robot " + robot, [&] {
    transaction([&] {
      Stmt s(db_, "UPDATE robots SET sequence=?, received=? WHERE robot_id=? AND session_id=?");
      s.bind(1, static_cast<std::int64_t>(sequence)).bind(2, received_unix).bind(3, robot).bind(4, session).run();
    });
  });
}

bool Store::save_alignment(const std::string& reference, const std::vector<Edge>& edges,
                           const std::vector<EdgeVerdict>& verdicts) {
  std::lock_guard<std::recursive_mutex> lock(mutex_);
  pending_.alignment.reset();  // superseded
  if (attempt("alignment", [&] { write_alignment(reference, edges, verdicts); })) return true;
  pending_.alignment.emplace(PendingAlignment{reference, edges, verdicts});
  health_.pending = pending_.size();
  return false;
}

bool Store::save_global(const GlobalMapOut& g, const std::vector<PoseOut>& poses) {
  std::lock_guard<std::recursive_mutex> lock(mutex_);
  pending_.global.reset();  // superseded
  if (attempt("global map " + std::to_string(g.version), [&] { write_global(g, poses); })) return true;
  pending_.global.emplace(g, poses);
  health_.pending = pending_.size();
  return false;
}

Store::Checkpoint Store::checkpoint() {
  std::lock_guard<std::recursive_mutex> lock(mutex_);
  Checkpoint c;
  if (db_ == nullptr || !writable_) return c;
  int log = 0, done = 0;
  c.ok = sqlite3_wal_checkpoint_v2(db_, nullptr, SQLITE_CHECKPOINT_PASSIVE, &log, &done) == SQLITE_OK;
  c.wal_frames = log < 0 ? 0 : static_cast<std::size_t>(log);
  c.checkpointed_frames = done < 0 ? 0 : static_cast<std::size_t>(done);
  return c;
}

bool Store::retry() {
  std::lock_guard<std::recursive_mutex> lock(mutex_);
  const std::size_t before = pending_.size();
  if (before == 0) return true;
  // Maps first, then alignments, then the global map that was built from them.
  for (auto it = pending_.maps.begin(); it != pending_.maps.end();) {
    const MapSample& m = it->second;
    if (!attempt("map of robot " + m.robot_id, [&] { write_map(m); })) return false;
    it = pending_.maps.erase(it);
  }
  if (pending_.alignment) {
    const PendingAlignment& a = *pending_.alignment;
    if (!attempt("alignment", [&] { write_alignment(a.reference, a.edges, a.verdicts); })) {
      return false;
    }
    pending_.alignment.reset();
  }
  if (pending_.global) {
    const GlobalMapOut& g = pending_.global->first;
    const std::vector<PoseOut>& poses = pending_.global->second;
    if (!attempt("global map " + std::to_string(g.version), [&] { write_global(g, poses); })) return false;
    pending_.global.reset();
  }
  spdlog::info("state store: {} pending writes persisted", before);
  settle();
  return true;
}

void Store::settle() {
  health_.pending = pending_.size();
  if (health_.ok || health_.pending != 0) return;
  health_.ok = true;
  health_.error.clear();
  spdlog::warn("state store works again: everything held in memory is persisted to {}", path_);
}

StoreHealth Store::health() const {
  std::lock_guard<std::recursive_mutex> lock(mutex_);
  StoreHealth h = health_;
  h.pending = pending_.size();
  return h;
}

void Store::write_map(const MapSample& m) {
  transaction([&] {
    Stmt s(db_, "INSERT OR REPLACE INTO robots VALUES(?,?,?,?,?,?,?,?,?,?,?)");
    s.bind(1, m.robot_id).bind(2, m.session_id).bind(3, static_cast<std::int64_t>(m.sequence));
    s.bind(4, m.frame_id).bind(5, m.resolution).bind(6, m.received_unix).bind(7, m.encoding);
    s.bind(8, std::int64_t{m.ros}).bind(9, std::int64_t{m.ros_binary}).bind(10, m.ros_id);
    s.bind(11, m.data.data(), m.data.size());
    s.run();
  });
}

void Store::write_alignment(const std::string& reference, const std::vector<Edge>& edges,
                            const std::vector<EdgeVerdict>& verdicts) {
  std::map<std::pair<std::string, std::string>, const EdgeVerdict*> verdict;
  for (const EdgeVerdict& v : verdicts) verdict[{v.target, v.source}] = &v;
  transaction([&] {
    Stmt(db_, "INSERT OR REPLACE INTO meta VALUES('reference', ?)").bind(1, reference).run();
    exec("DELETE FROM edges;");
    for (const Edge& e : edges) {
      Stmt s(db_, "INSERT INTO edges(target, source, T, fitness, inliers, overlap, pivot, information, state, "
                  "reason, evidence) VALUES(?,?,?,?,?,?,?,?,?,?,?)");
      s.bind(1, e.target).bind(2, e.source);
      bind_matrix(s, 3, e.T_target_source);
      s.bind(4, e.fitness).bind(5, static_cast<std::int64_t>(e.inliers)).bind(6, e.overlap);
      bind_matrix(s, 7, e.pivot_source);
      bind_matrix(s, 8, e.information);
      const auto v = verdict.find({e.target, e.source});
      const EdgeVerdict none{};
      const EdgeVerdict& ev = v == verdict.end() ? none : *v->second;
      s.bind(9, ev.state).bind(10, ev.reason).bind(11, ev.evidence).run();
    }
  });
}

void Store::save_attempt(const PairAttempt& a) {
  std::lock_guard<std::recursive_mutex> lock(mutex_);
  ensure_writable();
  transaction([&] {
    Stmt s(db_, "INSERT OR REPLACE INTO pair_attempts VALUES(?,?,?,?,?,?,?,?)");
    s.bind(1, a.robot_a).bind(2, a.robot_b).bind(3, a.kind).bind(4, static_cast<std::int64_t>(a.hash_a));
    s.bind(5, static_cast<std::int64_t>(a.hash_b)).bind(6, std::int64_t{a.accepted}).bind(7, a.reason);
    s.bind(8, a.stamp_unix).run();
  });
}

namespace {
/// Where the body of a global map whose payload is a plain `.bt` starts (just after its
/// header's "data" line); nullopt for any other encoding or a payload without that line.
std::optional<std::size_t> bt_body_offset(const GlobalMapOut& g) {
  if (g.encoding != "octomap-bt") return std::nullopt;
  constexpr std::string_view kDataLine = "\ndata\n";
  const std::size_t head = std::min<std::size_t>(g.data.size(), 4096);  // the header is a few lines
  const auto end = g.data.begin() + static_cast<std::ptrdiff_t>(head);
  const auto at = std::search(g.data.begin(), end, kDataLine.begin(), kDataLine.end());
  if (at == end) return std::nullopt;
  return static_cast<std::size_t>(at - g.data.begin()) + kDataLine.size();
}
}  // namespace

void Store::write_global(const GlobalMapOut& g, const std::vector<PoseOut>& poses) {
  transaction([&] {
    Stmt s(db_, "INSERT OR REPLACE INTO global_map VALUES(1,?,?,?,?,?,?,?,?)");
    s.bind(1, static_cast<std::int64_t>(g.version)).bind(2, g.stamp_unix).bind(3, g.frame_id);
    s.bind(4, g.resolution).bind(5, g.encoding).bind(6, g.data.data(), g.data.size());
    // The ROS 2 body is most often the `.bt` payload without its header: then it is not written
    // twice (an empty ros_body is taken from the payload on load).
    const auto body = bt_body_offset(g);
    const bool derived = body && g.data.size() - *body == g.ros_body.size() &&
                         std::equal(g.ros_body.begin(), g.ros_body.end(), g.data.begin() + static_cast<std::ptrdiff_t>(*body));
    s.bind(7, g.ros_body.data(), derived ? 0 : g.ros_body.size()).bind(8, contributors_json(g.contributors)).run();
    exec("DELETE FROM poses;");
    for (const PoseOut& p : poses) {
      const auto T = to_vec(p.T_global_robot);
      Stmt ps(db_, "INSERT INTO poses VALUES(?,?,?,?,?,?)");
      ps.bind(1, p.robot_id).bind(2, p.robot_frame).bind(3, T.data(), T.size() * sizeof(double));
      ps.bind(4, p.fitness).bind(5, p.quality).bind(6, static_cast<std::int64_t>(p.state)).run();
    }
  });
}

StoreSnapshot Store::load() {
  std::lock_guard<std::recursive_mutex> lock(mutex_);
  StoreSnapshot snap;
  if (db_ == nullptr) return snap;  // nothing could be opened (see the constructor's log)
  for (Stmt s(db_, "SELECT value FROM meta WHERE key='reference'"); s.step();) snap.reference = s.text(0);
  for (Stmt s(db_, "SELECT * FROM robots ORDER BY robot_id"); s.step();) {
    MapSample m;
    m.robot_id = m.topic_robot = s.text(0);
    m.session_id = s.text(1);
    m.sequence = static_cast<std::uint64_t>(s.integer(2));
    m.frame_id = s.text(3);
    m.resolution = s.real(4);
    m.received_unix = s.real(5);
    m.encoding = s.text(6);
    m.ros = s.integer(7) != 0;
    m.ros_binary = s.integer(8) != 0;
    m.ros_id = s.text(9);
    m.data = s.blob(10);
    snap.maps.push_back(std::move(m));
  }
  for (Stmt s(db_, "SELECT target, source, T, fitness, inliers, overlap, pivot, information, state, reason, "
                  "evidence FROM edges ORDER BY target, source");
       s.step();) {
    Edge e{s.text(0), s.text(1), from_blob(s.blob(2)), s.real(3)};
    e.inliers = static_cast<std::size_t>(std::max<std::int64_t>(0, s.integer(4)));
    e.overlap = s.real(5);
    e.pivot_source = matrix_from_blob<Eigen::Vector3d>(s.blob(6), Eigen::Vector3d::Zero());
    e.information = matrix_from_blob<Eigen::Matrix<double, 6, 6>>(s.blob(7), Eigen::Matrix<double, 6, 6>::Zero());
    snap.verdicts.push_back(EdgeVerdict{e.target, e.source, s.text(8), s.text(9), s.text(10)});
    snap.edges.push_back(std::move(e));
  }
  for (Stmt s(db_, "SELECT * FROM pair_attempts ORDER BY robot_a, robot_b"); s.step();) {
    snap.attempts.push_back(PairAttempt{s.text(0), s.text(1), s.text(2), static_cast<std::uint64_t>(s.integer(3)),
                                        static_cast<std::uint64_t>(s.integer(4)), s.integer(5) != 0, s.text(6),
                                        s.real(7)});
  }
  for (Stmt s(db_, "SELECT * FROM global_map WHERE id=1"); s.step();) {
    GlobalMapOut g;
    g.version = static_cast<std::uint64_t>(s.integer(1));
    g.stamp_unix = s.real(2);
    g.frame_id = s.text(3);
    g.resolution = s.real(4);
    g.encoding = s.text(5);
    g.data = s.blob(6);
    g.ros_body = s.blob(7);
    if (const auto body = bt_body_offset(g); g.ros_body.empty() && body) {
      g.ros_body.assign(g.data.begin() + static_cast<std::ptrdiff_t>(*body), g.data.end());
    }
    g.contributors = contributors_from(s.text(8));
    snap.global = std::move(g);
  }
  for (Stmt s(db_, "SELECT robot_id, frame, T, fitness, quality, state FROM poses"); s.step();) {
    snap.poses.push_back(PoseOut{s.text(0), s.text(1), from_blob(s.blob(2)), s.real(3), s.real(4),
                                 static_cast<PoseState>(s.integer(5))});
  }
  return snap;
}

}  // namespace mapmerge::server
