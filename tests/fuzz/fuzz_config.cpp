// libFuzzer target over the config loader (issue 7): mapmerge-server's parse_server_config(),
// which also reads core/align's config. See fuzz_config.hpp for the contract checked.
#include "fuzz_config.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  mapmerge::fuzz::parse_config_one(data, size);
  return 0;
}
