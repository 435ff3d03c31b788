#pragma once
/// The DDS domain id this test may use alone.
///
/// Under CTest every DDS test asks for one "domains" resource (tests/dds_domains.json) and
/// CTest exports it as CTEST_RESOURCE_GROUP_0_DOMAINS="id:N,slots:1". Run by hand, the test
/// falls back to MAPMERGE_TEST_DOMAIN or to a domain derived from its process id.

#include <cstdlib>
#include <string>

#include <unistd.h>

namespace mapmerge::test {

inline int dds_domain() {
  if (const char* group = std::getenv("CTEST_RESOURCE_GROUP_0_DOMAINS")) {
    const std::string s(group);
    const auto pos = s.find("id:");
    if (pos != std::string::npos) return std::atoi(s.c_str() + pos + 3);
  }
  if (const char* d = std::getenv("MAPMERGE_TEST_DOMAIN")) return std::atoi(d);
  return 1 + static_cast<int>(::getpid() % 100);
}

}  // namespace mapmerge::test
