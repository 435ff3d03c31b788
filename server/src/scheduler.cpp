#include "mapmerge/server/scheduler.hpp"

#include <algorithm>

#include <spdlog/spdlog.h>

namespace mapmerge::server {

Scheduler::Scheduler(int threads, Job job) : Scheduler(threads, std::move(job), nullptr) {}

Scheduler::Scheduler(int threads, Job job, IdleSource idle, int max_idle_jobs)
    : job_(std::move(job)), idle_(std::move(idle)) {
  const int n = std::max(1, threads);
  max_idle_jobs_ = max_idle_jobs > 0 ? max_idle_jobs : std::max(1, n - 1);
  for (int i = 0; i < n; ++i) threads_.emplace_back([this] { worker(); });
}

Scheduler::~Scheduler() { stop(); }

void Scheduler::enqueue_locked(const std::string& robot, Slot& slot) {
  if (slot.busy || slot.queued) return;  // picked up again when the running job ends
  slot.queued = true;
  ready_.push_back(robot);
  stats_.queued = ready_.size();
  stats_.max_queued = std::max(stats_.max_queued, ready_.size());
  cv_.notify_one();
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

bool Scheduler::idle_allowed_locked() const {
  return idle_ && idle_pending_ && ready_.empty() && idle_running_ < max_idle_jobs_;
}

void Scheduler::worker() {
  std::unique_lock<std::mutex> lock(mutex_);
  while (true) {
    cv_.wait(lock, [this] { return stopping_ || !ready_.empty() || idle_allowed_locked(); });
    if (stopping_) return;
    if (!ready_.empty()) {
      run_robot(lock);
    } else {
      run_idle(lock);
    }
  }
}

std::string Scheduler::next_locked() {
  // A waiting map goes before retries and refinements (a known robot's update is on the
  // fleet's latency path; a refinement of its previous map is not), but a retry passed over
  // kMaxSkips times goes first, so no robot waits forever behind a stream of maps.
  auto pick = ready_.begin();
  if (slots_[*pick].skipped < kMaxSkips) {
    const auto with_map = std::find_if(ready_.begin(), ready_.end(),
                                       [this](const std::string& r) { return slots_[r].map.has_value(); });
    if (with_map != ready_.end()) pick = with_map;
  }
  for (auto it = ready_.begin(); it != pick; ++it) ++slots_[*it].skipped;
  std::string robot = *pick;
  ready_.erase(pick);
  slots_[robot].skipped = 0;
  return robot;
}

void Scheduler::run_robot(std::unique_lock<std::mutex>& lock) {
  const std::string robot = next_locked();
  stats_.queued = ready_.size();
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
    cv_.notify_one();
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
  return stats_;
}

bool Scheduler::idle() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return ready_.empty() && running_ == 0 && idle_running_ == 0;
}

}  // namespace mapmerge::server
