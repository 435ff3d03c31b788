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

#include <sys/prctl.h>
#include <sys/wait.h>
#include <unistd.h>

namespace mapmerge::test {

/// Where a child's output goes.
struct Logs {
  std::string out;      ///< stdout (and stderr when `err` is empty)
  std::string err;      ///< stderr; empty: with stdout
  bool append = true;   ///< add to the files (a restarted server's log) or start them empty
  /// stdout and stderr interleaved in one file, appended to (restarts share a log).
  static Logs combined(const std::string& path) { return Logs{path, "", true}; }
  /// <prefix>.out and <prefix>.err, started empty (tests that parse the output of one run).
  static Logs split(const std::string& prefix) { return Logs{prefix + ".out", prefix + ".err", false}; }
};

class ChildProcess {
 public:
  /// Starts `program` (a path, or a name looked up in PATH) with `args`.
  ChildProcess(const std::string& program, const std::vector<std::string>& args, Logs logs) : logs_(std::move(logs)) {
    std::vector<std::string> argv_s{program};
    argv_s.insert(argv_s.end(), args.begin(), args.end());
    pid_ = ::fork();
    if (pid_ == 0) {
      ::setpgid(0, 0);
      ::prctl(PR_SET_PDEATHSIG, SIGKILL);  // never outlives a test that crashed (no destructor ran)
      std::vector<char*> argv;
      for (auto& a : argv_s) argv.push_back(a.data());
      argv.push_back(nullptr);
      const char* mode = logs_.append ? "a" : "w";
      if (FILE* out = std::fopen(logs_.out.c_str(), mode)) ::dup2(fileno(out), STDOUT_FILENO);
      FILE* err = logs_.err.empty() ? nullptr : std::fopen(logs_.err.c_str(), mode);
      ::dup2(err != nullptr ? fileno(err) : STDOUT_FILENO, STDERR_FILENO);
      ::execvp(argv_s[0].c_str(), argv.data());
      ::_exit(127);
    }
    if (pid_ > 0) ::setpgid(pid_, pid_);
  }
  ~ChildProcess() { kill(SIGKILL); }
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
  /// Sends `sig` to the group and waits for the exit as wait() does.
  int kill(int sig, std::chrono::milliseconds timeout = std::chrono::seconds(20)) {
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
  pid_t pid_ = -1;
  bool exited_ = false;
  int code_ = -1;
};

inline std::string server_binary() { return std::string(MAPMERGE_BINARY_DIR) + "/bin/mapmerge-server"; }

/// mapmerge-server of this build, its output in one log file.
class ServerProcess : public ChildProcess {
 public:
  ServerProcess(const std::vector<std::string>& args, const std::string& log_path)
      : ChildProcess(server_binary(), args, Logs::combined(log_path)) {}
};

}  // namespace mapmerge::test
