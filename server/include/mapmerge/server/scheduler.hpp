#pragma once
/// Runs per-robot work on a pool of threads with coalescing: each robot has one slot holding
/// its latest unprocessed map (a newer one replaces it: latest wins) and a retry flag. A robot
/// is queued at most once and processed by at most one thread at a time, so the queue is
/// bounded by the number of robots whatever the publishers' rates.
///
/// Robots with a waiting map are taken before robots waiting only for a retry (a global search
/// or a refinement), up to kMaxSkips times in a row for any one of those.
///
/// Idle work (e.g. extra pairwise alignments that give the pose graph cycles) runs only on spare
/// capacity: a worker asks for it only when no robot is waiting, and at most `max_idle_jobs`
/// idle jobs run at once, so with two or more threads one is always free for robot turns.
///
/// With a background lane (Lanes::threads > 0), background jobs (background(): alignments) and
/// idle work run on threads of their own, at a lower CPU priority (Lanes::nice), and the other
/// threads take only robots' maps and retries: a received map never waits behind an alignment,
/// and its check and fusion get the CPU first.

#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <functional>
#include <map>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "mapmerge/server/messages.hpp"

namespace mapmerge::server {

struct SchedulerStats {
  std::uint64_t submitted = 0;   ///< maps handed in [count]
  std::uint64_t coalesced = 0;   ///< maps replaced by a newer one before being processed [count]
  std::uint64_t jobs_run = 0;    ///< jobs finished [count]
  std::size_t queued = 0;        ///< robots waiting now [count]
  std::size_t max_queued = 0;    ///< most robots ever waiting at once [count]
  std::uint64_t idle_jobs_run = 0;  ///< idle jobs finished [count]
  std::size_t running = 0;       ///< jobs running now, robots' and idle ones [count]
};

class Scheduler {
 public:
  /// The background lane: its threads [count] (0: none, background jobs are robot retries) and
  /// the nice increment of those threads (Linux; 0 = the server's priority).
  struct Lanes {
    int threads = 0;
    int nice = 0;
  };

  /// The work for one robot: its newest map if one arrived, and whether a retry was asked.
  using Job = std::function<void(const std::string& robot, std::optional<MapSample> map, bool retry)>;

  /// Low-priority work: returns the next idle job, or an empty function when there is none.
  /// Called from worker threads without the scheduler's lock (must be thread-safe and must not
  /// hand out the same work twice).
  using IdleSource = std::function<std::function<void()>()>;

  Scheduler(int threads, Job job);
  /// Also runs idle work from `idle` on spare capacity (see above); 0 = threads - 1 (at least 1).
  Scheduler(int threads, Job job, IdleSource idle, int max_idle_jobs = 0);
  /// With a background lane; `max_idle_jobs` (0 = lanes.threads - 1, at least 1) counts there.
  Scheduler(int threads, Job job, IdleSource idle, int max_idle_jobs, Lanes lanes);
  ~Scheduler();  ///< stops and joins
  Scheduler(const Scheduler&) = delete;
  Scheduler& operator=(const Scheduler&) = delete;

  /// Hands in a robot's map (replacing any unprocessed one).
  void submit(MapSample map);
  /// Asks for `robot` to be processed again without a new map (e.g. new alignment partners).
  void retry(const std::string& robot);
  /// Runs the job for `key` (no map, retry = true) on the background lane, coalesced like a
  /// retry: asked again while queued, it runs once; while running, once more after.
  void background(const std::string& key);
  /// Tells the workers that idle work may be available (new alignments, changed maps).
  void kick_idle();
  /// Finishes running jobs, drops waiting ones, joins the threads. Idempotent.
  void stop();
  SchedulerStats stats() const;
  /// True when nothing is queued or running.
  bool idle() const;

 private:
  enum Lane : int { kForeground = 0, kBackground = 1 };
  struct Slot {
    Lane lane = kForeground;
    std::optional<MapSample> map;
    bool retry = false;
    bool busy = false;
    bool queued = false;
    int skipped = 0;  ///< times a robot with a waiting map was taken before this one
  };
  static constexpr int kMaxSkips = 4;
  void enqueue_locked(const std::string& robot, Slot& slot);
  std::string next_locked(Lane lane);  ///< removes and returns the key to run next (its queue not empty)
  void worker(Lane lane);
  bool idle_allowed_locked(Lane lane) const;
  bool nothing_ready_locked() const { return ready_[kForeground].empty() && ready_[kBackground].empty(); }
  void run_robot(Lane lane, std::unique_lock<std::mutex>& lock);
  void run_idle(std::unique_lock<std::mutex>& lock);

  Job job_;
  IdleSource idle_;
  int max_idle_jobs_ = 1;
  Lane idle_lane_ = kForeground;  ///< the lane whose threads run idle work
  bool idle_pending_ = false;  ///< idle work may exist (set by kick_idle and after idle jobs)
  int idle_running_ = 0;
  mutable std::mutex mutex_;
  std::condition_variable cv_;
  std::map<std::string, Slot> slots_;
  std::deque<std::string> ready_[2];  ///< per lane
  std::vector<std::thread> threads_;
  bool stopping_ = false;
  int running_ = 0;
  SchedulerStats stats_;
};

}  // namespace mapmerge::server
