#pragma once
// The config fuzz target's logic, shared with the regression test that replays
// tests/fuzz/regressions/config/.
//
// Input: the text of a mapmerge-server YAML config (its `align:` section is core/align's format).
// Contract checked on every input: parse_server_config() either returns a config or throws
// align::ConfigError with a message; any other exception escapes and the fuzzer reports it.
// Invariant on every accepted input: the align section dumped as YAML and parsed again is
// accepted and dumps to the same text.
#include <cstdint>
#include <cstdlib>
#include <string>

#include "mapmerge/align/config.hpp"
#include "mapmerge/server/config.hpp"

namespace mapmerge::fuzz {

/// Returns 1 if the config was accepted, 0 if rejected with a ConfigError; aborts on a broken
/// invariant.
inline int parse_config_one(const std::uint8_t* data, std::size_t size) {
  const std::string text(reinterpret_cast<const char*>(data), size);
  try {
    const auto config = server::parse_server_config(text);
    const auto dumped = align::dump_align_config_yaml(config.align);
    if (align::dump_align_config_yaml(align::parse_align_config(dumped)) != dumped) std::abort();
    return 1;
  } catch (const align::ConfigError& e) {
    if (std::string(e.what()).empty()) std::abort();  // a rejection always says why
    return 0;
  }
}

}  // namespace mapmerge::fuzz
