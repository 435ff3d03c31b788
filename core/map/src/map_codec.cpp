#include "mapmerge/map/map_codec.hpp"

#include <cstring>
#include <sstream>

#include "codec_detail.hpp"
#include "mapmerge/map/map_io.hpp"
#include "tree_scan.hpp"

namespace mapmerge {
namespace {

using detail::format_double;
using detail::is_zstd;
using detail::kBinaryFirstLine;
using detail::kFullFirstLine;
using detail::rejected;
using detail::starts_with;

constexpr std::string_view kTreeId = "OcTree";

/// The tree OctoMap builds from a body, read straight from the bytes: OcTree::readBinaryData's
/// for a `.bt` body (same nodes, same values: inner nodes the maximum of their children), and
/// OcTree::readData's for a `.ot` body (same nodes, same log-odds, inner nodes as stored).
/// OctoMap reads each node through two istream calls and counts the whole tree again at the
/// end; this reads a body the pre-pass has validated (at most 16 levels, finite values) at
/// ~1.5x the speed (fr_079.bt: ~80 -> ~54 ms; the paper's pair, two `.ot` files read at once:
/// ~80 -> ~50 ms). Stops at a body that ends early (the node count check then rejects the tree).
class BodyTree : public octomap::OcTree {
 public:
  BodyTree(double res, bool binary, const std::uint8_t* body, std::size_t size)
      : octomap::OcTree(res), next_(body), end_(body + size) {
    root = new octomap::OcTreeNode();
    tree_size = 1;  // createNodeChild counts the rest
    if (binary) {
      read_binary(root);
    } else {
      read_full(root);
    }
    size_changed = true;
  }

 private:
  void read_binary(octomap::OcTreeNode* node) {
    if (end_ - next_ < 2) {
      next_ = end_;
      return;
    }
    const std::uint8_t* record = next_;
    next_ += 2;
    node->setLogOdds(clamping_thres_max);  // as OctoMap: inner nodes start occupied
    unsigned inner = 0;
    for (unsigned i = 0; i < 8; ++i) {
      const unsigned bits = detail::binary_child_code(record, i);  // 1 free, 2 occupied, 3 inner
      if (bits == 0) continue;
      octomap::OcTreeNode* child = createNodeChild(node, i);
      child->setLogOdds(bits == 1 ? clamping_thres_min : clamping_thres_max);
      if (bits == 3) inner |= 1U << i;
    }
    for (unsigned i = 0; i < 8; ++i) {
      if ((inner & (1U << i)) == 0) continue;
      octomap::OcTreeNode* child = getNodeChild(node, i);
      read_binary(child);
      child->setLogOdds(child->getMaxChildLogOdds());
    }
  }

  static constexpr std::ptrdiff_t kFullNodeBytes = sizeof(float) + 1;  ///< log-odds, child bits

  void read_full(octomap::OcTreeNode* node) {
    if (end_ - next_ < kFullNodeBytes) {
      next_ = end_;
      return;
    }
    float value = 0.0F;
    std::memcpy(&value, next_, sizeof(value));
    const unsigned children = next_[sizeof(float)];
    next_ += kFullNodeBytes;
    node->setLogOdds(value);
    for (unsigned i = 0; i < 8; ++i) {
      if ((children & (1U << i)) != 0) read_full(createNodeChild(node, i));
    }
  }

  const std::uint8_t* next_;
  const std::uint8_t* end_;
};

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

/// With `build_tree` false a body is only checked: the result holds the body, no tree.
DecodeResult decode_body(double res, bool binary, const std::uint8_t* body, std::size_t size,
                         std::optional<std::uint64_t> claimed_nodes, const DecodeLimits& limits,
                         bool build_tree = true) {
  const detail::TreeScan scan = binary ? detail::scan_binary_body(body, size, limits.max_nodes)
                                       : detail::scan_full_body(body, size, limits.max_nodes);
  if (scan.error != DecodeError::kNone) return rejected(scan.error, scan.reason);
  if (claimed_nodes && *claimed_nodes != scan.num_nodes) {
    return rejected(DecodeError::kNodeCountMismatch,
                    "header claims " + std::to_string(*claimed_nodes) + " nodes, body holds " +
                        std::to_string(scan.num_nodes));
  }
  if (scan.occupied_voxels > limits.max_occupied_voxels) {
    return rejected(DecodeError::kVolumeTooLarge,
                    std::to_string(scan.occupied_voxels) + " occupied full-resolution voxels, limit " +
                        std::to_string(limits.max_occupied_voxels));
  }
  if (scan.fusion_work > limits.max_fusion_work) {
    return rejected(DecodeError::kVolumeTooLarge,
                    "leaves so large that fusing them would cost ~" +
                        std::to_string(static_cast<long long>(scan.fusion_work)) + " voxel visits, limit " +
                        format_double(limits.max_fusion_work));
  }
  DecodeResult result;
  if (scan.num_nodes == 0 || scan.root_only) {
    result.tree = std::make_unique<octomap::OcTree>(res);
    result.empty = true;  // a root without children carries no map information
    return result;
  }
  if (!build_tree) {  // checked only: the map is held as its body (HeldMap builds the tree on demand)
    (binary ? result.binary_body : result.full_body) =
        std::make_shared<const std::vector<std::uint8_t>>(body, body + size);
    result.num_nodes = scan.num_nodes;
    return result;
  }
  result.tree = std::make_unique<BodyTree>(res, binary, body, size);
  if (binary) result.binary_body = std::make_shared<const std::vector<std::uint8_t>>(body, body + size);
  result.num_nodes = result.tree->size();
  if (result.num_nodes != scan.num_nodes) {
    return rejected(DecodeError::kMalformedTree, "the body built a tree of " +
                                                     std::to_string(result.num_nodes) +
                                                     " nodes where the pre-pass counted " +
                                                     std::to_string(scan.num_nodes));
  }
  return result;
}

DecodeResult decode_file_bytes(const std::uint8_t* data, std::size_t size, bool binary,
                               const DecodeLimits& limits, bool build_tree = true, double* res_out = nullptr) {
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
  detail::Header header;
  const std::string_view first_line = binary ? kBinaryFirstLine : kFullFirstLine;
  if (auto bad = detail::parse_header(data, size, first_line, limits, header)) return std::move(*bad);
  if (auto bad = check_id_and_resolution(header.id, header.res, limits)) return std::move(*bad);
  if (header.size_overflow || header.size > limits.max_nodes) {
    return rejected(DecodeError::kTooManyNodes,
                    "header claims " + (header.size_overflow ? std::string("more than 2^64")
                                                             : std::to_string(header.size)) +
                        " nodes, limit " + std::to_string(limits.max_nodes));
  }
  if (res_out != nullptr) *res_out = header.res;
  return decode_body(header.res, binary, data + header.body_offset, size - header.body_offset,
                     header.size, limits, build_tree);
}

/// decode_map(); with `build_tree` false a body is only checked. `res_out`: the header's
/// resolution, once parsed.
DecodeResult decode_payload(const std::uint8_t* data, std::size_t size, Encoding encoding, const DecodeLimits& limits,
                            bool build_tree, double* res_out) {
  switch (encoding) {
    case Encoding::kOctomapBt: return decode_file_bytes(data, size, true, limits, build_tree, res_out);
    case Encoding::kOctomapOt: return decode_file_bytes(data, size, false, limits, build_tree, res_out);
    case Encoding::kOctomapBtZstd: {
      if (auto too_large = check_size(size, limits, "compressed payload")) return std::move(*too_large);
      std::vector<std::uint8_t> raw;
      if (auto bad = detail::inflate(data, size, limits, raw)) return std::move(*bad);
      return decode_file_bytes(raw.data(), raw.size(), true, limits, build_tree, res_out);
    }
  }
  return rejected(DecodeError::kUnknownEncoding, "unknown encoding value");
}

/// decode_tree_body(), the same way.
DecodeResult tree_body(std::string_view id, double resolution, bool binary, const std::uint8_t* data,
                       std::size_t size, const DecodeLimits& limits, bool build_tree) {
  if (auto too_large = check_size(size, limits, "tree body")) return std::move(*too_large);
  if (auto bad = check_id_and_resolution(id, resolution, limits)) return std::move(*bad);
  return decode_body(resolution, binary, data, size, std::nullopt, limits, build_tree);
}

/// What check_map() keeps of a decode_body() result.
CheckedMap to_checked(DecodeResult r, double res) {
  CheckedMap out;
  out.error = r.error;
  out.reason = std::move(r.reason);
  out.empty = r.empty;
  if (!r.ok() || r.empty) return out;
  if (r.tree) {
    out.map = std::make_shared<const HeldMap>(std::shared_ptr<const octomap::OcTree>(std::move(r.tree)),
                                              std::move(r.binary_body));
  } else if (r.full_body) {
    out.map = detail::held_checked_full_body(res, std::move(r.full_body), r.num_nodes);
  } else {
    out.map = detail::held_checked_body(res, std::move(r.binary_body), r.num_nodes);
  }
  return out;
}

}  // namespace

namespace detail {

std::unique_ptr<octomap::OcTree> build_checked_binary_tree(double res, const std::vector<std::uint8_t>& body) {
  return std::make_unique<BodyTree>(res, true, body.data(), body.size());
}

std::unique_ptr<octomap::OcTree> build_checked_full_tree(double res, const std::vector<std::uint8_t>& body) {
  return std::make_unique<BodyTree>(res, false, body.data(), body.size());
}

}  // namespace detail

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
    case DecodeError::kVolumeTooLarge: return "volume_too_large";
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
  return detail::deflate(raw, options.zstd_level);
}

DecodeResult decode_map(const std::uint8_t* data, std::size_t size, Encoding encoding,
                        const DecodeLimits& limits) {
  return decode_payload(data, size, encoding, limits, true, nullptr);
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
  return tree_body(id, resolution, binary, data, size, limits, true);
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

CheckedMap check_map(const std::uint8_t* data, std::size_t size, Encoding encoding, const DecodeLimits& limits) {
  double res = 0.0;  // the header's, set by decode_payload
  DecodeResult r = decode_payload(data, size, encoding, limits, false, &res);
  return to_checked(std::move(r), res);
}

CheckedMap check_map(const std::vector<std::uint8_t>& bytes, std::string_view encoding, const DecodeLimits& limits) {
  const std::optional<Encoding> parsed = parse_encoding(encoding);
  if (!parsed) return to_checked(decode_map(bytes, encoding, limits), 0.0);  // the same rejection
  return check_map(bytes.data(), bytes.size(), *parsed, limits);
}

CheckedMap check_tree_body(std::string_view id, double resolution, bool binary, const std::vector<std::uint8_t>& data,
                           const DecodeLimits& limits) {
  return to_checked(tree_body(id, resolution, binary, data.data(), data.size(), limits, false), resolution);
}

}  // namespace mapmerge
