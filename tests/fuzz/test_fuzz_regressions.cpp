// Replays tests/fuzz/regressions/ through the fuzz targets' logic: no crash, no broken invariant,
// and each input accepted or rejected as its name says (`accept-*`, `reject-*`).
//   regressions/         map payloads (fuzz_decode.hpp)
//   regressions/config/  server config texts (fuzz_config.hpp)
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <functional>
#include <iterator>

#include "fuzz_config.hpp"
#include "fuzz_decode.hpp"

namespace {

using Target = std::function<int(const std::uint8_t*, std::size_t)>;

/// Replays every stored input of `dir` through `target`; returns how many were replayed.
int replay(const std::filesystem::path& dir, const Target& target) {
  int replayed = 0;
  for (const auto& entry : std::filesystem::directory_iterator(dir)) {
    const std::string name = entry.path().filename().string();
    if (!entry.is_regular_file() || name == "README.md") continue;
    std::ifstream in(entry.path(), std::ios::binary);
    const std::vector<std::uint8_t> bytes{std::istreambuf_iterator<char>(in), {}};
    const int accepted = target(bytes.data(), bytes.size());
    if (name.rfind("reject-", 0) == 0) {
      EXPECT_EQ(accepted, 0) << name;
    } else if (name.rfind("accept-", 0) == 0) {
      EXPECT_GT(accepted, 0) << name;
    }
    ++replayed;
  }
  return replayed;
}

TEST(FuzzRegressions, EveryStoredMapInputBehaves) {
  EXPECT_GE(replay(MAPMERGE_FUZZ_REGRESSIONS, mapmerge::fuzz::decode_one), 13);
}

TEST(FuzzRegressions, EveryStoredConfigInputBehaves) {
  EXPECT_GE(replay(std::filesystem::path(MAPMERGE_FUZZ_REGRESSIONS) / "config", mapmerge::fuzz::parse_config_one), 1);
}

}  // namespace
