#include "mapmerge/server/scheduler.hpp"

#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>

#include <spdlog/spdlog.h>

namespace mapmerge::server {
namespace {

/// Lowers the calling thread's CPU priority by `increment` nice levels (Linux: a thread's nice
/// value is its own). Raising it again would need privileges, so a lane's threads keep theirs.
void lower_thread_priority(int increment) {
  if (increment <= 0) return;
  const auto tid = static_cast<id_t>(gettid());
  errno = 0;
  const int now = getpriority(PRIO_PROCESS, tid);
  if (errno == 0 && setpriority(PRIO_PROCESS, tid, std::min(19, now + increment)) == 0) return;
  spdlog::warn("merge thread keeps the server's CPU priority (merge.merge_nice not applied): {}", std::strerror(errno));
}

}  // namespace

Scheduler::Scheduler(int threads, Job job) : Scheduler(threads, std::move(job), nullptr) {}

Scheduler::Scheduler(int threads, Job job, IdleSource idle, int max_idle_jobs)
    : Scheduler(threads, std::move(job), std::move(idle), max_idle_jobs, Lanes{}) {}

Scheduler::Scheduler(int threads, Job job, IdleSource idle, int max_idle_jobs, Lanes lanes)
    : job_(std::move(job)), idle_(std::move(idle)) {
  const int n = std::max(1, threads);
  const int background = std::max(0, lanes.threads);
  idle_lane_ = background > 0 ? kBackground : kForeground;
  max_idle_jobs_ = max_idle_jobs > 0 ? max_idle_jobs : std::max(1, (background > 0 ? background : n) - 1);
  for (int i = 0; i < n; ++i) threads_.emplace_back([this] { worker(kForeground); });
  for (int i = 0; i < background; ++i) {
    threads_.emplace_back([this, nice = lanes.nice] {
      lower_thread_priority(nice);
      worker(kBackground);
    });
  }
}

Scheduler::~Scheduler() { stop(); }

void Scheduler::enqueue_locked(const std::string& robot, Slot& slot) {
  if (slot.busy || slot.queued) return;  // picked up again when the running job ends
  slot.queued = true;
  ready_[slot.lane].push_back(robot);
  stats_.queued = ready_[kForeground].size() + ready_[kBackground].size();
  stats_.max_queued = std::max(stats_.max_queued, stats_.queued);
  cv_.notify_all();  // the lanes' threads wait on one condition
}

void Scheduler::submit(MapSample map) {
  std::lock_guard<std::mutex> lock(mutex_);
  if (stopping_) return;
  const std::string robot = map.robot_id;
  Slot& slot = slots_[robot];
  ++stats_.submitted;
  if (slot.map) ++stats_.coalesced;
  slot.map = std::move(map);
  enqueue_locked(robot, slot);
}

void Scheduler::retry(const std::string& robot) {
  std::lock_guard<std::mutex> lock(mutex_);
  if (stopping_) return;
  Slot& slot = slots_[robot];
  slot.retry = true;
  enqueue_locked(robot, slot);
}

void Scheduler::background(const std::string& key) {
  std::lock_guard<std::mutex> lock(mutex_);
  if (stopping_) return;
  Slot& slot = slots_[key];
  if (idle_lane_ == kBackground && !slot.busy && !slot.queued) slot.lane = kBackground;  // else the robots' lane
  slot.retry = true;
  enqueue_locked(key, slot);
}

bool Scheduler::idle_allowed_locked(Lane lane) const {
  return idle_ && lane == idle_lane_ && idle_pending_ && ready_[lane].empty() && idle_running_ < max_idle_jobs_;
}

void Scheduler::worker(Lane lane) {
  std::unique_lock<std::mutex> lock(mutex_);
  while (true) {
    cv_.wait(lock, [&] { return stopping_ || !ready_[lane].empty() || idle_allowed_locked(lane); });
    if (stopping_) return;
    if (!ready_[lane].empty()) {
      run_robot(lane, lock);
    } else {
      run_idle(lock);
    }
  }
}

std::string Scheduler::next_locked(Lane lane) {
  // A waiting map goes before retries and refinements (a known robot's update is on the
  // fleet's latency path; a refinement of its previous map is not), but a retry passed over
  // kMaxSkips times goes first, so no robot waits forever behind a stream of maps.
  std::deque<std::string>& ready = ready_[lane];
  auto pick = ready.begin();
  if (slots_[*pick].skipped < kMaxSkips) {
    const auto with_map = std::find_if(ready.begin(), ready.end(),
                                       [this](const std::string& r) { return slots_[r].map.has_value(); });
    if (with_map != ready.end()) pick = with_map;
  }
  for (auto it = ready.begin(); it != pick; ++it) ++slots_[*it].skipped;
  std::string robot = *pick;
  ready.erase(pick);
  slots_[robot].skipped = 0;
  return robot;
}

void Scheduler::run_robot(Lane lane, std::unique_lock<std::mutex>& lock) {
  const std::string robot = next_locked(lane);
  stats_.queued = ready_[kForeground].size() + ready_[kBackground].size();
  Slot& slot = slots_[robot];
  std::optional<MapSample> map = std::move(slot.map);
  slot.map.reset();
  const bool retry = slot.retry;
  slot.retry = false;
  slot.queued = false;
  slot.busy = true;
  ++running_;
  lock.unlock();
  try {
    job_(robot, std::move(map), retry);
  } catch (const std::exception& e) {
    spdlog::error("job for robot {} failed: {}", robot, e.what());
  }
  lock.lock();
  --running_;
  ++stats_.jobs_run;
  Slot& after = slots_[robot];
  after.busy = false;
  if (after.map || after.retry) enqueue_locked(robot, after);
}

void Scheduler::run_idle(std::unique_lock<std::mutex>& lock) {
  idle_pending_ = false;
  ++idle_running_;
  lock.unlock();
  bool ran = false;
  try {
    if (std::function<void()> job = idle_()) {
      ran = true;
      job();
    }
  } catch (const std::exception& e) {
    spdlog::error("idle job failed: {}", e.what());
  }
  lock.lock();
  --idle_running_;
  if (ran) {
    ++stats_.idle_jobs_run;
    idle_pending_ = true;  // there may be more
    cv_.notify_all();
  }
}

void Scheduler::kick_idle() {
  std::lock_guard<std::mutex> lock(mutex_);
  if (stopping_ || !idle_) return;
  idle_pending_ = true;
  cv_.notify_all();
}

void Scheduler::stop() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    stopping_ = true;
  }
  cv_.notify_all();
  for (auto& t : threads_) {
    if (t.joinable()) t.join();
  }
  threads_.clear();
}

SchedulerStats Scheduler::stats() const {
  std::lock_guard<std::mutex> lock(mutex_);
  SchedulerStats s = stats_;
  s.running = static_cast<std::size_t>(running_ + idle_running_);
  return s;
}

bool Scheduler::idle() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return nothing_ready_locked() && running_ == 0 && idle_running_ == 0;
}

}  // namespace mapmerge::server
