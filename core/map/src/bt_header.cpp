#include <algorithm>
#include <cstdlib>

#include "codec_detail.hpp"

namespace mapmerge::detail {
namespace {

std::string_view trim(std::string_view s) {
  while (!s.empty() && (s.front() == ' ' || s.front() == '\t')) s.remove_prefix(1);
  while (!s.empty() && (s.back() == ' ' || s.back() == '\t' || s.back() == '\r')) {
    s.remove_suffix(1);
  }
  return s;
}

/// Parses one "keyword value" line into `header`; returns an error text or "".
std::string parse_header_line(std::string_view line, Header& header, bool& done) {
  const std::size_t space = line.find_first_of(" \t");
  const std::string_view key = line.substr(0, space);
  const std::string_view value = space == std::string_view::npos ? "" : trim(line.substr(space));
  if (key == "data" && value.empty()) {
    done = true;
    return "";
  }
  if (value.empty() || value.find_first_of(" \t") != std::string_view::npos) {
    return "malformed header line '" + std::string(line.substr(0, 64)) + "'";
  }
  if (key == "id" && header.id.empty()) {
    header.id = std::string(value);
  } else if (key == "res" && !header.has_res) {
    const std::string text(value);
    char* end = nullptr;
    header.res = std::strtod(text.c_str(), &end);
    if (end != text.c_str() + text.size()) return "res '" + text.substr(0, 32) + "' is not a number";
    header.has_res = true;
  } else if (key == "size" && !header.has_size) {
    for (const char c : value) {
      if (c < '0' || c > '9') return "size '" + std::string(value.substr(0, 32)) + "' is not a count";
      if (header.size > (UINT64_MAX - 9) / 10) header.size_overflow = true;
      header.size = header.size * 10 + static_cast<std::uint64_t>(c - '0');
    }
    header.has_size = true;
  } else {
    return "unexpected or repeated header keyword '" + std::string(key.substr(0, 32)) + "'";
  }
  return "";
}

}  // namespace

std::optional<DecodeResult> parse_header(const std::uint8_t* data, std::size_t size,
                                         std::string_view first_line, const DecodeLimits& limits,
                                         Header& header) {
  const std::size_t window = std::min(size, limits.max_header_bytes);
  const std::string_view text(reinterpret_cast<const char*>(data), window);
  std::size_t pos = 0;
  bool done = false;
  for (int line_no = 0; !done; ++line_no) {
    const std::size_t eol = text.find('\n', pos);
    if (eol == std::string_view::npos) {
      return rejected(DecodeError::kBadHeader, "no 'data' line within the first " +
                                                   std::to_string(window) + " bytes");
    }
    const std::string_view line = trim(text.substr(pos, eol - pos));
    pos = eol + 1;
    if (line_no == 0) {
      if (line.substr(0, first_line.size()) != first_line) {
        return rejected(DecodeError::kBadHeader,
                        "first line is not '" + std::string(first_line) + "'");
      }
      continue;
    }
    if (line.empty() || line.front() == '#') continue;
    const std::string error = parse_header_line(line, header, done);
    if (!error.empty()) return rejected(DecodeError::kBadHeader, error);
  }
  if (header.id.empty()) return rejected(DecodeError::kBadHeader, "header has no id");
  if (!header.has_res) return rejected(DecodeError::kBadHeader, "header has no res");
  if (!header.has_size) return rejected(DecodeError::kBadHeader, "header has no size");
  header.body_offset = pos;
  return std::nullopt;
}

/// Runs the pre-pass over a validated header's body, then lets OctoMap build the tree.

}  // namespace mapmerge::detail
