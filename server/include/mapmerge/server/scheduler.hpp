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
};

class Scheduler {
 public:
  /// The work for one robot: its newest map if one arrived, and whether a retry was asked.
  using Job = std::function<void(const std::string& robot, std::optional<MapSample> map, bool retry)>;

  /// Low-priority work: returns the next idle job, or an empty function when there is none.
  /// Called from worker threads without the scheduler's lock (must be thread-safe and must not
  /// hand out the same work twice).
  using IdleSource = std::function<std::function<void()>()>;

  Scheduler(int threads, Job job);
  /// Also runs idle work from `idle` on spare capacity (see above); 0 = threads - 1 (at least 1).
  Scheduler(int threads, Job job, IdleSource idle, int max_idle_jobs = 0);
  ~Scheduler();  ///< stops and joins
  Scheduler(const Scheduler&) = delete;
  Scheduler& operator=(const Scheduler&) = delete;

  /// Hands in a robot's map (replacing any unprocessed one).
  void submit(MapSample map);
  /// Asks for `robot` to be processed again without a new map (e.g. new alignment partners).
  void retry(const std::string& robot);
  /// Tells the workers that idle work may be available (new alignments, changed maps).
  void kick_idle();
  /// Finishes running jobs, drops waiting ones, joins the threads. Idempotent.
  void stop();
  SchedulerStats stats() const;
  /// True when nothing is queued or running.
  bool idle() const;

 private:
  struct Slot {
    std::optional<MapSample> map;
    bool retry = false;
    bool busy = false;
    bool queued = false;
    int skipped = 0;  ///< times a robot with a waiting map was taken before this one
  };
  static constexpr int kMaxSkips = 4;
  void enqueue_locked(const std::string& robot, Slot& slot);
  std::string next_locked();  ///< removes and returns the robot to run next (ready_ not empty)
  void worker();
  bool idle_allowed_locked() const;
  void run_robot(std::unique_lock<std::mutex>& lock);
  void run_idle(std::unique_lock<std::mutex>& lock);

  Job job_;
  IdleSource idle_;
  int max_idle_jobs_ = 1;
  bool idle_pending_ = false;  ///< idle work may exist (set by kick_idle and after idle jobs)
  int idle_running_ = 0;
  mutable std::mutex mutex_;
  std::condition_variable cv_;
  std::map<std::string, Slot> slots_;
  std::deque<std::string> ready_;
  std::vector<std::thread> threads_;
  bool stopping_ = false;
  int running_ = 0;
  SchedulerStats stats_;
};

}  // namespace mapmerge::server
