#pragma once
/// A program as a child process of a test or bench (mapmerge-server, the CLIs, `fastdds
/// discovery`): in its own process group (signals reach its children too), its stdout and
/// stderr appended to log files, ended with SIGKILL when the object goes.

#include <chrono>
#include <csignal>
#include <cstdio>
#include <fstream>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include <fcntl.h>
#include <sys/prctl.h>
#include <sys/wait.h>
#include <unistd.h>

namespace mapmerge::test {

/// Where a child's output goes.
struct Logs {
  std::string out;      ///< stdout (and stderr when `err` is empty)
  std::string err;      ///< stderr; empty: with stdout
  bool append = true;   ///< add to the files (a restarted server's log) or start them empty
  /// Combined output through a pipe that the parent copies into `out`: the child's own file
  /// limits (RLIMIT_FSIZE) then never apply to its log.
  bool piped = false;
  /// stdout and stderr interleaved in one file, appended to (restarts share a log).
  static Logs combined(const std::string& path) { return Logs{path, "", true, false}; }
  /// As combined(), through a pipe.
  static Logs combined_piped(const std::string& path) { return Logs{path, "", true, true}; }
  /// <prefix>.out and <prefix>.err, started empty (tests that parse the output of one run).
  static Logs split(const std::string& prefix) { return Logs{prefix + ".out", prefix + ".err", false, false}; }
};

class ChildProcess {
 public:
  /// Starts `program` (a path, or a name looked up in PATH) with `args`.
  ChildProcess(const std::string& program, const std::vector<std::string>& args, Logs logs) : logs_(std::move(logs)) {
    std::vector<std::string> argv_s{program};
    argv_s.insert(argv_s.end(), args.begin(), args.end());
    int pipe_fds[2] = {-1, -1};
    if (logs_.piped && ::pipe2(pipe_fds, O_CLOEXEC) != 0) pipe_fds[0] = pipe_fds[1] = -1;
    pid_ = ::fork();
    if (pid_ == 0) {
      ::setpgid(0, 0);
      ::prctl(PR_SET_PDEATHSIG, SIGKILL);  // never outlives a test that crashed (no destructor ran)
      std::vector<char*> argv;
      for (auto& a : argv_s) argv.push_back(a.data());
      argv.push_back(nullptr);
      const char* mode = logs_.append ? "a" : "w";
      if (pipe_fds[1] >= 0) {
        ::dup2(pipe_fds[1], STDOUT_FILENO);
        ::close(pipe_fds[0]);
      } else if (FILE* out = std::fopen(logs_.out.c_str(), mode)) {
        ::dup2(fileno(out), STDOUT_FILENO);
      }
      FILE* err = logs_.err.empty() ? nullptr : std::fopen(logs_.err.c_str(), mode);
      ::dup2(err != nullptr ? fileno(err) : STDOUT_FILENO, STDERR_FILENO);
      ::execvp(argv_s[0].c_str(), argv.data());
      ::_exit(127);
    }
    if (pid_ > 0) ::setpgid(pid_, pid_);
    if (pipe_fds[1] >= 0) {
      ::close(pipe_fds[1]);
      copier_ = std::thread([fd = pipe_fds[0], path = logs_.out] {
        std::ofstream out(path, std::ios::app);
        char buf[4096];
        for (ssize_t n; (n = ::read(fd, buf, sizeof buf)) > 0;) out.write(buf, n).flush();
        ::close(fd);
      });
    }
  }
  ~ChildProcess() {
    kill(SIGKILL);
    if (copier_.joinable()) copier_.join();  // EOF once the child is gone
  }
  ChildProcess(const ChildProcess&) = delete;
  ChildProcess& operator=(const ChildProcess&) = delete;

  bool running() {
    if (pid_ <= 0 || exited_) return false;
    int status = 0;
    if (::waitpid(pid_, &status, WNOHANG) == pid_) {
      exited_ = true;
      code_ = WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status);
    }
    return !exited_;
  }
  /// Waits up to `timeout` for the exit; returns the exit code (128 + signal when killed), or -1
  /// when it was still running (it is then killed).
  int wait(std::chrono::milliseconds timeout) {
    const auto deadline = std::chrono::steady_clock::now() + timeout;
    while (running() && std::chrono::steady_clock::now() < deadline) {
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    if (running()) {
      ::kill(-pid_, SIGKILL);
      ::waitpid(pid_, nullptr, 0);
      exited_ = true;
      code_ = -1;
    }
    return code_;
  }
  /// Sends `sig` to the group and waits for the exit as wait() does. The default wait covers a
  /// server finishing a global search that was running when the signal came (the search is not
  /// cancelled midway: up to ~30 s under ASan).
  int kill(int sig, std::chrono::milliseconds timeout = std::chrono::seconds(60)) {
    signal(sig);
    return wait(timeout);
  }
  /// Signals the whole group (children included) without waiting.
  void signal(int sig) {
    if (running()) ::kill(-pid_, sig);
  }
  pid_t pid() const { return pid_; }
  std::string out() const { return slurp(logs_.out); }
  std::string err() const { return logs_.err.empty() ? out() : slurp(logs_.err); }
  /// Everything it wrote (stderr after stdout when split).
  std::string log() const { return logs_.err.empty() ? out() : out() + err(); }

 private:
  static std::string slurp(const std::string& path) {
    std::ifstream in(path);
    std::stringstream ss;
    ss << in.rdbuf();
    return ss.str();
  }
  Logs logs_;
  std::thread copier_;  ///< piped logs: copies the child's output into the log file
  pid_t pid_ = -1;
  bool exited_ = false;
  int code_ = -1;
};

inline std::string server_binary() { return std::string(MAPMERGE_BINARY_DIR) + "/bin/mapmerge-server"; }

/// mapmerge-server of this build, its output in one log file (through a pipe: file size limits
/// set on the server for a test never cut its log).
class ServerProcess : public ChildProcess {
 public:
  ServerProcess(const std::vector<std::string>& args, const std::string& log_path)
      : ChildProcess(server_binary(), args, Logs::combined_piped(log_path)) {}
};

}  // namespace mapmerge::test
