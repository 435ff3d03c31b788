#include "mapmerge/server/scheduler.hpp"

#include <algorithm>

#include <spdlog/spdlog.h>

namespace mapmerge::server {

Scheduler::Scheduler(int threads, Job job) : job_(std::move(job)) {
  for (int i = 0; i < std::max(1, threads); ++i) threads_.emplace_back([this] { worker(); });
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

void Scheduler::worker() {
  std::unique_lock<std::mutex> lock(mutex_);
  while (true) {
    cv_.wait(lock, [this] { return stopping_ || !ready_.empty(); });
    if (stopping_) return;
    const std::string robot = ready_.front();
    ready_.pop_front();
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
  return ready_.empty() && running_ == 0;
}

}  // namespace mapmerge::server
