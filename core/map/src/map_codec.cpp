#include "mapmerge/map/map_codec.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <istream>
#include <sstream>
#include <streambuf>

#include <zstd.h>

#include "mapmerge/map/map_io.hpp"
#include "tree_scan.hpp"

namespace mapmerge {
namespace {

constexpr std::string_view kBinaryFirstLine = "# Octomap OcTree binary file";
constexpr std::string_view kFullFirstLine = "# Octomap OcTree file";
constexpr std::string_view kTreeId = "OcTree";
constexpr std::uint8_t kZstdMagic[4] = {0x28, 0xB5, 0x2F, 0xFD};

/// An istream over bytes we do not own (OctoMap reads from std::istream only).
class ByteStreamBuf : public std::streambuf {
 public:
  ByteStreamBuf(const std::uint8_t* data, std::size_t size) {
    char* begin = reinterpret_cast<char*>(const_cast<std::uint8_t*>(data));
    setg(begin, begin, begin + size);
  }
};

DecodeResult rejected(DecodeError error, std::string reason) {
  DecodeResult result;
  result.error = error;
  result.reason = std::string(to_string(error)) + ": " + reason;
  return result;
}

std::string format_double(double value) {
  char buf[32];
  std::snprintf(buf, sizeof(buf), "%g", value);
  return buf;
}

bool starts_with(const std::uint8_t* data, std::size_t size, std::string_view prefix) {
  return size >= prefix.size() && std::memcmp(data, prefix.data(), prefix.size()) == 0;
}

bool is_zstd(const std::uint8_t* data, std::size_t size) {
  return size >= 4 && std::memcmp(data, kZstdMagic, 4) == 0;
}

std::optional<DecodeResult> check_size(std::size_t size, const DecodeLimits& limits,
                                       const char* what) {
  if (size < limits.max_bytes) return std::nullopt;
  return rejected(DecodeError::kTooLarge, std::string(what) + " of " + std::to_string(size) +
                                              " bytes reaches the limit of " +
                                              std::to_string(limits.max_bytes));
}

std::optional<DecodeResult> check_id_and_resolution(std::string_view id, double res,
                                                    const DecodeLimits& limits) {
  if (id != kTreeId) {
    return rejected(DecodeError::kUnknownTreeId,
                    "tree id '" + std::string(id.substr(0, 64)) + "' is not 'OcTree'");
  }
  if (!std::isfinite(res) || res < limits.min_resolution || res > limits.max_resolution) {
    return rejected(DecodeError::kBadResolution,
                    "resolution " + format_double(res) + " m outside [" +
                        format_double(limits.min_resolution) + ", " +
                        format_double(limits.max_resolution) + "] m");
  }
  return std::nullopt;
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
DecodeResult decode_body(double res, bool binary, const std::uint8_t* body, std::size_t size,
                         std::optional<std::uint64_t> claimed_nodes, const DecodeLimits& limits) {
  const detail::TreeScan scan = binary ? detail::scan_binary_body(body, size, limits.max_nodes)
                                       : detail::scan_full_body(body, size, limits.max_nodes);
  if (scan.error != DecodeError::kNone) return rejected(scan.error, scan.reason);
  if (claimed_nodes && *claimed_nodes != scan.num_nodes) {
    return rejected(DecodeError::kNodeCountMismatch,
                    "header claims " + std::to_string(*claimed_nodes) + " nodes, body holds " +
                        std::to_string(scan.num_nodes));
  }
  DecodeResult result;
  result.tree = std::make_unique<octomap::OcTree>(res);
  if (scan.num_nodes == 0 || scan.root_only) {
    result.empty = true;  // a root without children carries no map information
    return result;
  }
  ByteStreamBuf buf(body, size);
  std::istream in(&buf);
  if (binary) {
    result.tree->readBinaryData(in);
  } else {
    result.tree->readData(in);
  }
  result.num_nodes = result.tree->size();
  if (!in || result.num_nodes != scan.num_nodes) {
    return rejected(DecodeError::kMalformedTree, "OctoMap read " +
                                                     std::to_string(result.num_nodes) +
                                                     " nodes where the pre-pass counted " +
                                                     std::to_string(scan.num_nodes));
  }
  return result;
}

DecodeResult decode_file_bytes(const std::uint8_t* data, std::size_t size, bool binary,
                               const DecodeLimits& limits) {
  if (auto too_large = check_size(size, limits, "payload")) return std::move(*too_large);
  const Encoding encoding = binary ? Encoding::kOctomapBt : Encoding::kOctomapOt;
  if (is_zstd(data, size)) {
    return rejected(DecodeError::kEncodingMismatch,
                    std::string("payload is zstd-compressed but the encoding is ") +
                        to_string(encoding));
  }
  const std::string_view other = binary ? kFullFirstLine : kBinaryFirstLine;
  if (starts_with(data, size, other) && !starts_with(data, size, binary ? kBinaryFirstLine : kFullFirstLine)) {
    return rejected(DecodeError::kEncodingMismatch,
                    std::string("payload is a ") + (binary ? ".ot" : ".bt") +
                        " file but the encoding is " + to_string(encoding));
  }
  Header header;
  const std::string_view first_line = binary ? kBinaryFirstLine : kFullFirstLine;
  if (auto bad = parse_header(data, size, first_line, limits, header)) return std::move(*bad);
  if (auto bad = check_id_and_resolution(header.id, header.res, limits)) return std::move(*bad);
  if (header.size_overflow || header.size > limits.max_nodes) {
    return rejected(DecodeError::kTooManyNodes,
                    "header claims " + (header.size_overflow ? std::string("more than 2^64")
                                                             : std::to_string(header.size)) +
                        " nodes, limit " + std::to_string(limits.max_nodes));
  }
  return decode_body(header.res, binary, data + header.body_offset, size - header.body_offset,
                     header.size, limits);
}

/// Inflates zstd frame(s) into `out`, never past limits.max_bytes.
std::optional<DecodeResult> inflate(const std::uint8_t* data, std::size_t size,
                                    const DecodeLimits& limits, std::vector<std::uint8_t>& out) {
  if (!is_zstd(data, size)) {
    if (starts_with(data, size, "# Octomap")) {
      return rejected(DecodeError::kEncodingMismatch,
                      "payload is an uncompressed OctoMap but the encoding is octomap-bt+zstd");
    }
    return rejected(DecodeError::kDecompressionFailed, "payload is not a zstd frame");
  }
  const unsigned long long declared = ZSTD_getFrameContentSize(data, size);
  if (declared == ZSTD_CONTENTSIZE_ERROR) {
    return rejected(DecodeError::kDecompressionFailed, "corrupt zstd frame header");
  }
  if (declared != ZSTD_CONTENTSIZE_UNKNOWN && declared >= limits.max_bytes) {
    return rejected(DecodeError::kTooLarge, "zstd frame declares " + std::to_string(declared) +
                                                " bytes, limit " +
                                                std::to_string(limits.max_bytes));
  }
  std::unique_ptr<ZSTD_DCtx, decltype(&ZSTD_freeDCtx)> ctx(ZSTD_createDCtx(), &ZSTD_freeDCtx);
  if (!ctx) return rejected(DecodeError::kDecompressionFailed, "cannot create zstd context");
  out.clear();
  out.resize(declared != ZSTD_CONTENTSIZE_UNKNOWN ? static_cast<std::size_t>(declared) + 1
                                                  : std::min<std::size_t>(4 * size, limits.max_bytes));
  ZSTD_inBuffer in{data, size, 0};
  std::size_t produced = 0;
  std::size_t last = 1;
  while (in.pos < in.size || last != 0) {
    if (produced == out.size()) {
      if (out.size() >= limits.max_bytes) {
        return rejected(DecodeError::kTooLarge, "decompresses to " + std::to_string(limits.max_bytes) +
                                                    " bytes or more (the limit)");
      }
      out.resize(std::min(limits.max_bytes, 2 * out.size() + 4096));
    }
    ZSTD_outBuffer ob{out.data(), out.size(), produced};
    const std::size_t before_in = in.pos;
    last = ZSTD_decompressStream(ctx.get(), &ob, &in);
    if (ZSTD_isError(last)) {
      return rejected(DecodeError::kDecompressionFailed, ZSTD_getErrorName(last));
    }
    const bool progress = ob.pos != produced || in.pos != before_in;
    produced = ob.pos;
    if (!progress && produced < out.size()) {
      return rejected(DecodeError::kDecompressionFailed, "zstd frame is incomplete");
    }
  }
  if (produced >= limits.max_bytes) {
    return rejected(DecodeError::kTooLarge, "decompresses to " + std::to_string(produced) +
                                                " bytes or more, limit " +
                                                std::to_string(limits.max_bytes));
  }
  out.resize(produced);
  return std::nullopt;
}

}  // namespace

const char* to_string(Encoding encoding) {
  switch (encoding) {
    case Encoding::kOctomapBt: return "octomap-bt";
    case Encoding::kOctomapBtZstd: return "octomap-bt+zstd";
    case Encoding::kOctomapOt: return "octomap-ot";
  }
  return "?";
}

std::optional<Encoding> parse_encoding(std::string_view name) {
  for (const Encoding e : {Encoding::kOctomapBt, Encoding::kOctomapBtZstd, Encoding::kOctomapOt}) {
    if (name == to_string(e)) return e;
  }
  return std::nullopt;
}

const char* to_string(DecodeError error) {
  switch (error) {
    case DecodeError::kNone: return "ok";
    case DecodeError::kUnknownEncoding: return "unknown_encoding";
    case DecodeError::kEncodingMismatch: return "encoding_mismatch";
    case DecodeError::kTooLarge: return "too_large";
    case DecodeError::kDecompressionFailed: return "decompression_failed";
    case DecodeError::kBadHeader: return "bad_header";
    case DecodeError::kUnknownTreeId: return "unknown_tree_id";
    case DecodeError::kBadResolution: return "bad_resolution";
    case DecodeError::kTooManyNodes: return "too_many_nodes";
    case DecodeError::kNodeCountMismatch: return "node_count_mismatch";
    case DecodeError::kTruncated: return "truncated";
    case DecodeError::kTrailingBytes: return "trailing_bytes";
    case DecodeError::kTooDeep: return "too_deep";
    case DecodeError::kMalformedTree: return "malformed_tree";
    case DecodeError::kBadValue: return "bad_value";
  }
  return "?";
}

std::vector<std::uint8_t> encode_map(const octomap::OcTree& tree, Encoding encoding) {
  return encode_map(tree, encoding, EncodeOptions{});
}

std::vector<std::uint8_t> encode_map(const octomap::OcTree& tree, Encoding encoding,
                                     const EncodeOptions& options) {
  std::vector<std::uint8_t> raw;
  if (encoding == Encoding::kOctomapOt) {
    std::ostringstream out(std::ios::binary);
    if (!tree.write(out)) throw MapError("cannot serialise the octree");
    const std::string text = out.str();
    raw.assign(text.begin(), text.end());
  } else {
    // Same bytes as OcTree::writeBinaryConst, without its recursion and stderr chatter.
    detail::append_binary_header(tree, raw);
    detail::append_binary_body(tree, raw);
  }
  if (encoding != Encoding::kOctomapBtZstd) return raw;
  // The frame carries its content size (lets the receiver reject oversize before inflating)
  // and a checksum (a corrupted payload fails to decompress instead of yielding other bytes).
  std::unique_ptr<ZSTD_CCtx, decltype(&ZSTD_freeCCtx)> ctx(ZSTD_createCCtx(), &ZSTD_freeCCtx);
  if (!ctx) throw MapError("cannot create a zstd context");
  ZSTD_CCtx_setParameter(ctx.get(), ZSTD_c_compressionLevel, options.zstd_level);
  ZSTD_CCtx_setParameter(ctx.get(), ZSTD_c_checksumFlag, 1);
  std::vector<std::uint8_t> packed(ZSTD_compressBound(raw.size()));
  const std::size_t n = ZSTD_compress2(ctx.get(), packed.data(), packed.size(), raw.data(), raw.size());
  if (ZSTD_isError(n)) throw MapError(std::string("zstd compression failed: ") + ZSTD_getErrorName(n));
  packed.resize(n);
  return packed;
}

DecodeResult decode_map(const std::uint8_t* data, std::size_t size, Encoding encoding,
                        const DecodeLimits& limits) {
  switch (encoding) {
    case Encoding::kOctomapBt: return decode_file_bytes(data, size, true, limits);
    case Encoding::kOctomapOt: return decode_file_bytes(data, size, false, limits);
    case Encoding::kOctomapBtZstd: {
      if (auto too_large = check_size(size, limits, "compressed payload")) return std::move(*too_large);
      std::vector<std::uint8_t> raw;
      if (auto bad = inflate(data, size, limits, raw)) return std::move(*bad);
      return decode_file_bytes(raw.data(), raw.size(), true, limits);
    }
  }
  return rejected(DecodeError::kUnknownEncoding, "unknown encoding value");
}

DecodeResult decode_map(const std::vector<std::uint8_t>& bytes, Encoding encoding,
                        const DecodeLimits& limits) {
  return decode_map(bytes.data(), bytes.size(), encoding, limits);
}

DecodeResult decode_map(const std::vector<std::uint8_t>& bytes, std::string_view encoding,
                        const DecodeLimits& limits) {
  const std::optional<Encoding> parsed = parse_encoding(encoding);
  if (!parsed) {
    return rejected(DecodeError::kUnknownEncoding,
                    "encoding '" + std::string(encoding.substr(0, 64)) +
                        "' is not octomap-bt, octomap-bt+zstd or octomap-ot");
  }
  return decode_map(bytes, *parsed, limits);
}

DecodeResult decode_tree_body(std::string_view id, double resolution, bool binary,
                              const std::uint8_t* data, std::size_t size,
                              const DecodeLimits& limits) {
  if (auto too_large = check_size(size, limits, "tree body")) return std::move(*too_large);
  if (auto bad = check_id_and_resolution(id, resolution, limits)) return std::move(*bad);
  return decode_body(resolution, binary, data, size, std::nullopt, limits);
}

DecodeResult decode_tree_body(std::string_view id, double resolution, bool binary,
                              const std::vector<std::uint8_t>& data, const DecodeLimits& limits) {
  return decode_tree_body(id, resolution, binary, data.data(), data.size(), limits);
}

std::vector<std::uint8_t> encode_tree_body(const octomap::OcTree& tree, bool binary) {
  if (binary) {
    std::vector<std::uint8_t> body;
    detail::append_binary_body(tree, body);
    return body;
  }
  std::ostringstream out(std::ios::binary);
  tree.writeData(out);
  if (!out) throw MapError("cannot serialise the octree body");
  const std::string raw = out.str();
  return {raw.begin(), raw.end()};
}

}  // namespace mapmerge
