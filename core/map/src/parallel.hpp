#pragma once
/// Running one piece of work on a few threads at once (internal to mapmerge_core).

#include <algorithm>
#include <future>
#include <system_error>
#include <thread>
#include <vector>

namespace mapmerge::detail {

/// The threads a parallel piece of core/map's work uses by default: one per core, at most 4,
/// at least 1.
inline unsigned default_threads() { return std::max(1U, std::min(4U, std::thread::hardware_concurrency())); }

/// Runs `work` on this thread and on up to `threads - 1` helper threads, and returns when all
/// are done. `work` takes its items from a shared (atomic) index until none is left; should no
/// helper thread be had, this thread does it all. Exceptions of a helper are rethrown here.
template <class Work>
void run_parallel(unsigned threads, Work& work) {
  std::vector<std::future<void>> helpers;
  for (unsigned t = 1; t < threads; ++t) {
    try {
      helpers.push_back(std::async(std::launch::async, [&work] { work(); }));
    } catch (const std::system_error&) {
      break;  // no thread to be had: this one does the rest
    }
  }
  work();
  for (auto& h : helpers) h.get();
}

}  // namespace mapmerge::detail
