#pragma once
/// CPU time and memory of a live process, read from /proc (benches of mapmerge-server).

#include <fstream>
#include <iterator>
#include <sstream>
#include <string>
#include <vector>

#include <sys/types.h>
#include <unistd.h>

namespace mapmerge::bench {

struct ProcStats {
  double cpu_s = 0.0;     ///< utime + stime [s]
  double rss_mb = 0.0;    ///< VmRSS now [MiB]
  double hwm_mb = 0.0;    ///< VmHWM, peak resident set [MiB]
  int threads = 0;        ///< Threads
};

inline ProcStats proc_stats(pid_t pid) {
  ProcStats p;
  std::ifstream stat("/proc/" + std::to_string(pid) + "/stat");
  const std::string s((std::istreambuf_iterator<char>(stat)), std::istreambuf_iterator<char>());
  if (s.rfind(')') != std::string::npos) {
    std::istringstream rest(s.substr(s.rfind(')') + 2));
    const std::vector<std::string> f((std::istream_iterator<std::string>(rest)), std::istream_iterator<std::string>());
    const double ticks = static_cast<double>(sysconf(_SC_CLK_TCK));
    if (f.size() > 12) p.cpu_s = (std::stod(f[11]) + std::stod(f[12])) / ticks;
  }
  std::ifstream status("/proc/" + std::to_string(pid) + "/status");
  for (std::string line; std::getline(status, line);) {
    if (line.rfind("VmHWM:", 0) == 0) p.hwm_mb = std::stod(line.substr(6)) / 1024.0;
    if (line.rfind("VmRSS:", 0) == 0) p.rss_mb = std::stod(line.substr(6)) / 1024.0;
    if (line.rfind("Threads:", 0) == 0) p.threads = std::stoi(line.substr(8));
  }
  return p;
}

}  // namespace mapmerge::bench
