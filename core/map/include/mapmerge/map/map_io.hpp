#pragma once
/// Reading and writing OctoMap files.

#include <cstdint>
#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

#include <octomap/OcTree.h>

namespace mapmerge {

/// Thrown for input that is not a readable occupancy map (clear message, never an abort).
class MapError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

/// Loads an OcTree from a `.bt` (binary, max-likelihood) or `.ot` (full, with log-odds) file.
/// Throws MapError for a missing file, another extension, or bytes that are not such a map
/// (validated by decode_map() with default DecodeLimits before OctoMap parses anything).
std::unique_ptr<octomap::OcTree> read_octree_file(const std::string& path);

class HeldMap;

/// Loads a `.bt` or `.ot` file as read_octree_file() does, with the same checks and errors, but
/// keeps a `.bt` file's body undecoded (mapmerge::HeldMap: its octree is built on first use).
std::shared_ptr<const HeldMap> read_map_file(const std::string& path);

/// Whether write_octree_file() writes `path` as a full `.ot` file (with log-odds), not a `.bt` one.
bool is_ot_path(const std::string& path);

/// Writes `tree` as a `.bt` file (`.ot`, with log-odds, when the path ends so). Throws MapError when the file cannot be written.
void write_octree_file(const octomap::OcTree& tree, const std::string& path);

/// Writes a `.bt` payload (header + body, as GlobalFusion::encode() gives it) to `path` as it is.
/// Throws MapError when the file cannot be written.
void write_bt_file(const std::vector<std::uint8_t>& bt, const std::string& path);

}  // namespace mapmerge
