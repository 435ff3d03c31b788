// Replays tests/fuzz/regressions/ through the fuzz target's logic: no crash, no broken invariant,
// and each input accepted or rejected as its name says.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <iterator>

#include "fuzz_decode.hpp"

namespace {

TEST(FuzzRegressions, EveryStoredInputBehaves) {
  const std::filesystem::path dir = std::filesystem::path(MAPMERGE_FUZZ_REGRESSIONS);
  int replayed = 0;
  for (const auto& entry : std::filesystem::directory_iterator(dir)) {
    const std::string name = entry.path().filename().string();
    if (name == "README.md") continue;
    std::ifstream in(entry.path(), std::ios::binary);
    const std::vector<std::uint8_t> bytes{std::istreambuf_iterator<char>(in), {}};
    const int accepted = mapmerge::fuzz::decode_one(bytes.data(), bytes.size());
    if (name.rfind("reject-", 0) == 0) {
      EXPECT_EQ(accepted, 0) << name;
    } else if (name.rfind("accept-", 0) == 0) {
      EXPECT_GT(accepted, 0) << name;
    }
    ++replayed;
  }
  EXPECT_GE(replayed, 13);
}

}  // namespace
