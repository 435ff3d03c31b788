#pragma once
/// Pieces of the wire codec shared by its translation units (internal to mapmerge_core).

#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "mapmerge/map/map_codec.hpp"

namespace mapmerge::detail {

constexpr std::string_view kBinaryFirstLine = "# Octomap OcTree binary file";
constexpr std::string_view kFullFirstLine = "# Octomap OcTree file";
constexpr std::uint8_t kZstdMagic[4] = {0x28, 0xB5, 0x2F, 0xFD};

inline DecodeResult rejected(DecodeError error, const std::string& reason) {
  DecodeResult result;
  result.error = error;
  result.reason = std::string(to_string(error)) + ": " + reason;
  return result;
}

inline std::string format_double(double value) {
  char buf[32];
  std::snprintf(buf, sizeof(buf), "%g", value);
  return buf;
}

inline bool starts_with(const std::uint8_t* data, std::size_t size, std::string_view prefix) {
  return size >= prefix.size() && std::memcmp(data, prefix.data(), prefix.size()) == 0;
}

inline bool is_zstd(const std::uint8_t* data, std::size_t size) {
  return size >= 4 && std::memcmp(data, kZstdMagic, 4) == 0;
}

/// The text header of a `.bt`/`.ot` file, parsed strictly (OctoMap's own writer's form).
struct Header {
  std::string id;
  double res = std::nan("");
  std::uint64_t size = 0;
  bool has_res = false;
  bool has_size = false;
  bool size_overflow = false;
  std::size_t body_offset = 0;
};

/// Parses the text header of a `.bt` (first line `first_line`) into `header`, strictly: known
/// keywords once each, within limits.max_header_bytes. Returns the rejection, if any.
std::optional<DecodeResult> parse_header(const std::uint8_t* data, std::size_t size,
                                         std::string_view first_line, const DecodeLimits& limits,
                                         Header& header);

/// Inflates zstd frame(s) into `out`, never past limits.max_bytes. Returns the rejection, if any.
std::optional<DecodeResult> inflate(const std::uint8_t* data, std::size_t size,
                                    const DecodeLimits& limits, std::vector<std::uint8_t>& out);

/// The octree of a binary body that passed decode_body()'s pre-pass (never for unchecked bytes).
std::unique_ptr<octomap::OcTree> build_checked_binary_tree(double res, const std::vector<std::uint8_t>& body);
/// The octree of a full body that passed decode_body()'s pre-pass (OcTree::readData's nodes).
std::unique_ptr<octomap::OcTree> build_checked_full_tree(double res, const std::vector<std::uint8_t>& body);

/// Compresses `raw` into one zstd frame with content size and checksum. Throws MapError.
std::vector<std::uint8_t> deflate(const std::vector<std::uint8_t>& raw, int level);

}  // namespace mapmerge::detail
