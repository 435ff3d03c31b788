#pragma once
/// Map payloads on the wire: OctoMap's own bytes, validated before OctoMap's parser sees them.
///
/// OctoMap 1.9.7's readers trust their input (truncated bodies, absurd resolutions, node counts
/// checked after parsing, one recursion per tree level). decode_map() therefore runs a
/// non-recursive pre-pass over the header and the whole bit stream first and hands OctoMap only
/// bytes that are known to describe a well-formed tree of bounded size and depth.

#include <cstddef>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include <octomap/OcTree.h>

#include "mapmerge/map/held_map.hpp"

namespace mapmerge {

/// How a map is serialised in a payload. The strings are what travels in the message's
/// `encoding` field.
enum class Encoding {
  kOctomapBt,      ///< "octomap-bt": a `.bt` file (header + OcTree::writeBinary body)
  kOctomapBtZstd,  ///< "octomap-bt+zstd": the same bytes compressed as zstd frame(s)
  kOctomapOt,      ///< "octomap-ot": a `.ot` file (header + full body with float log-odds)
};

/// The wire name of an encoding ("octomap-bt", ...).
const char* to_string(Encoding encoding);
/// Parses a wire name; nullopt for anything else (compared exactly, case-sensitive).
std::optional<Encoding> parse_encoding(std::string_view name);

/// Bounds a payload must respect. Every check runs before OctoMap allocates anything.
struct DecodeLimits {
  std::size_t max_bytes = 100'000'000;  ///< payloads (and decompressed payloads) of this many
                                        ///< bytes or more are rejected [bytes]
  std::size_t max_nodes = 16'000'000;   ///< most tree nodes accepted (inner + leaves); ~50-80 B
                                        ///< of RAM each once parsed [nodes]
  std::uint64_t max_occupied_voxels = 50'000'000;  ///< most occupied space, in full-resolution
                                        ///< voxels (pruned leaves expanded: what to_points and
                                        ///< render produce); fr_079 has 0.4 M [voxels]
  double max_fusion_work = 5e8;         ///< most target-voxel visits fusing the map at its own
                                        ///< resolution may cost (FuseConfig::max_work; huge pruned
                                        ///< leaves); fr_079 needs ~2e7 [-]
  double min_resolution = 0.001;        ///< smallest accepted voxel edge [m]
  double max_resolution = 10.0;         ///< largest accepted voxel edge [m]
  std::size_t max_header_bytes = 4096;  ///< longest accepted text header [bytes]
};

/// Why a payload was rejected. to_string() gives a stable snake_case name for counters.
enum class DecodeError {
  kNone,                 ///< accepted
  kUnknownEncoding,      ///< the encoding field names no supported encoding
  kEncodingMismatch,     ///< the bytes are of another encoding than the field says
  kTooLarge,             ///< payload or its decompressed size reaches DecodeLimits::max_bytes
  kDecompressionFailed,  ///< the zstd payload is corrupt or incomplete
  kBadHeader,            ///< the text header is missing, malformed or too long
  kUnknownTreeId,        ///< tree id other than "OcTree"
  kBadResolution,        ///< resolution not finite or outside [min_resolution, max_resolution]
  kTooManyNodes,         ///< claimed or actual node count above DecodeLimits::max_nodes
  kNodeCountMismatch,    ///< the header's size differs from the nodes in the body
  kTruncated,            ///< the body ends before the tree it describes (e.g. mid-node)
  kTrailingBytes,        ///< bytes left over after the complete tree
  kTooDeep,              ///< the tree goes below OctoMap's 16 levels
  kMalformedTree,        ///< a structurally impossible node (e.g. inner node without children)
  kBadValue,             ///< a log-odds value that is not finite (full `.ot` format)
  kVolumeTooLarge,       ///< occupied space or leaf sizes beyond max_occupied_voxels or
                         ///< max_fusion_work (valid bytes, but too costly to process)
};

const char* to_string(DecodeError error);

/// Outcome of decoding: a tree, or the reason it was rejected (never an abort, never a throw for
/// hostile bytes).
struct DecodeResult {
  std::unique_ptr<octomap::OcTree> tree;  ///< the map; null when rejected
  DecodeError error = DecodeError::kNone;
  std::string reason;         ///< one line for the log; empty when accepted
  bool empty = false;         ///< accepted, but the map holds no nodes (valid, flag it upstream)
  std::size_t num_nodes = 0;  ///< nodes in the decoded tree (inner + leaves)
  /// The binary body (OcTree::writeBinaryData's bytes) the tree was read from, validated: set for
  /// octomap-bt, octomap-bt+zstd and binary ROS 2 bodies of non-empty maps; null for full (`.ot`)
  /// bodies. GlobalFusion diffs two such bodies instead of walking two trees.
  std::shared_ptr<const std::vector<std::uint8_t>> binary_body;
  /// The full body (OcTree::writeData's bytes), validated: set only by check_map() and
  /// check_tree_body() of a full body, which build no tree.
  std::shared_ptr<const std::vector<std::uint8_t>> full_body;

  bool ok() const { return error == DecodeError::kNone; }
};

/// Options of encode_map().
struct EncodeOptions {
  int zstd_level = 3;  ///< zstd compression level for kOctomapBtZstd (1 fast .. 19 small)
};

/// Serialises `tree` as the given encoding (OcTree::writeBinaryConst: the tree is not modified;
/// prune it first for the smallest payload). Throws MapError if compression fails.
std::vector<std::uint8_t> encode_map(const octomap::OcTree& tree, Encoding encoding);
std::vector<std::uint8_t> encode_map(const octomap::OcTree& tree, Encoding encoding,
                                     const EncodeOptions& options);

/// Validates and decodes a payload of the given encoding.
DecodeResult decode_map(const std::vector<std::uint8_t>& bytes, Encoding encoding,
                        const DecodeLimits& limits);
/// Same, with the encoding as it travels on the wire (unknown names give kUnknownEncoding).
DecodeResult decode_map(const std::vector<std::uint8_t>& bytes, std::string_view encoding,
                        const DecodeLimits& limits);
/// Same, over a raw buffer (no copy).
DecodeResult decode_map(const std::uint8_t* data, std::size_t size, Encoding encoding,
                        const DecodeLimits& limits);

/// The ROS 2 octomap_msgs/Octomap path: `id` (must be "OcTree"), `resolution`, `binary` (true:
/// OcTree::writeBinaryData body; false: OcTree::writeData body with float log-odds) and `data`,
/// the bare tree body without any text header.
DecodeResult decode_tree_body(std::string_view id, double resolution, bool binary,
                              const std::vector<std::uint8_t>& data, const DecodeLimits& limits);
DecodeResult decode_tree_body(std::string_view id, double resolution, bool binary,
                              const std::uint8_t* data, std::size_t size,
                              const DecodeLimits& limits);

/// The bare body for an octomap_msgs/Octomap message (binary: writeBinaryData; else writeData).
std::vector<std::uint8_t> encode_tree_body(const octomap::OcTree& tree, bool binary);

/// A payload validated as decode_map() validates it, kept undecoded where it can be (HeldMap).
struct CheckedMap {
  std::shared_ptr<const HeldMap> map;  ///< the map; null when rejected or empty
  DecodeError error = DecodeError::kNone;
  std::string reason;  ///< one line for the log; empty when accepted
  bool empty = false;  ///< accepted, but the map holds no nodes
  bool ok() const { return error == DecodeError::kNone; }
};

/// decode_map()'s checks, accepting and rejecting exactly the same payloads, without building
/// the map's tree: the HeldMap keeps the binary (octomap-bt, octomap-bt+zstd) or full (`.ot`)
/// body and builds the tree on first use. O(bytes).
CheckedMap check_map(const std::uint8_t* data, std::size_t size, Encoding encoding, const DecodeLimits& limits);
CheckedMap check_map(const std::vector<std::uint8_t>& bytes, std::string_view encoding, const DecodeLimits& limits);
/// decode_tree_body()'s checks, the same way (ROS 2 bodies, binary or full, are kept undecoded).
CheckedMap check_tree_body(std::string_view id, double resolution, bool binary, const std::vector<std::uint8_t>& data,
                           const DecodeLimits& limits);

}  // namespace mapmerge
