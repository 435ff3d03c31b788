// Linked into every test executable (mapmerge_test_common): when a test process is still running
// shortly before its CTest timeout (MAPMERGE_TEST_TIMEOUT_S, set by mapmerge_test()), it prints
// every thread's stack (gdb) and aborts, so that a hang shows in the log where it is instead of
// CTest's bare "Timeout" (which kills the process with its buffered output unwritten).
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <thread>

#include <unistd.h>

namespace {

struct HangWatchdog {
  HangWatchdog() {
    std::setvbuf(stdout, nullptr, _IOLBF, 0);  // GoogleTest's lines reach the log as they are written
    const char* timeout_s = std::getenv("MAPMERGE_TEST_TIMEOUT_S");
    if (timeout_s == nullptr) return;  // not run by CTest (e.g. test discovery)
    const long timeout = std::atol(timeout_s);
    const long margin = timeout / 10 > 30 ? timeout / 10 : 30;  // room for gdb to attach and print
    if (timeout <= margin) return;
    std::thread([timeout, after = timeout - margin] {
      std::this_thread::sleep_for(std::chrono::seconds(after));
      std::fflush(stdout);
      std::fprintf(stderr, "\n*** hang watchdog: still running after %ld s (CTest timeout %ld s); every thread:\n",
                   after, timeout);
      const std::string gdb = "gdb -batch -nx -p " + std::to_string(::getpid()) +
                              " -ex 'thread apply all bt' 1>&2 2>/dev/null";
      [[maybe_unused]] const int rc = std::system(gdb.c_str());
      std::fprintf(stderr, "*** hang watchdog: aborting\n");
      std::abort();
    }).detach();
  }
};

const HangWatchdog watchdog;

}  // namespace
