#pragma once
/// A program (mapmerge-server, `fastdds discovery`) as a child process of a test, in its own
/// process group (signals reach its children too), its output in a log file.

#include <chrono>
#include <csignal>
#include <fstream>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include <sys/prctl.h>
#include <sys/wait.h>
#include <unistd.h>

namespace mapmerge::test {

inline std::string server_binary() { return std::string(MAPMERGE_BINARY_DIR) + "/bin/mapmerge-server"; }

class ChildProcess {
 public:
  ChildProcess(const std::string& program, const std::vector<std::string>& args, const std::string& log_path)
      : log_path_(log_path) {
    std::vector<std::string> argv_s{program};
    argv_s.insert(argv_s.end(), args.begin(), args.end());
    pid_ = ::fork();
    if (pid_ == 0) {
      ::setpgid(0, 0);
      ::prctl(PR_SET_PDEATHSIG, SIGKILL);  // never outlives a test that crashed (no destructor ran)
      std::vector<char*> argv;
      for (auto& a : argv_s) argv.push_back(a.data());
      argv.push_back(nullptr);
      if (FILE* log = std::fopen(log_path.c_str(), "a")) {
        ::dup2(fileno(log), STDOUT_FILENO);
        ::dup2(fileno(log), STDERR_FILENO);
      }
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
  /// Sends `sig` and waits for the exit; returns the exit code (128 + signal when killed).
  int kill(int sig, std::chrono::seconds timeout = std::chrono::seconds(20)) {
    if (running()) ::kill(-pid_, sig);
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
  /// Signals the whole group (children included) without waiting.
  void signal_group(int sig) { if (pid_ > 0) ::kill(-pid_, sig); }
  pid_t pid() const { return pid_; }
  std::string log() const {
    std::ifstream in(log_path_);
    std::stringstream ss;
    ss << in.rdbuf();
    return ss.str();
  }

 private:
  std::string log_path_;
  pid_t pid_ = -1;
  bool exited_ = false;
  int code_ = -1;
};

class ServerProcess : public ChildProcess {
 public:
  ServerProcess(const std::vector<std::string>& args, const std::string& log_path)
      : ChildProcess(server_binary(), args, log_path) {}
};

}  // namespace mapmerge::test
