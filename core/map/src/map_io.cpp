#include "mapmerge/map/map_io.hpp"

#include <fstream>
#include <vector>

#include "mapmerge/map/held_map.hpp"
#include "mapmerge/map/map_codec.hpp"

namespace mapmerge {
namespace {

bool ends_with(const std::string& s, const std::string& suffix) {
  return s.size() >= suffix.size() && s.compare(s.size() - suffix.size(), suffix.size(), suffix) == 0;
}

std::vector<std::uint8_t> read_bytes(const std::string& path, std::size_t max_bytes) {
  std::ifstream in(path, std::ios::binary | std::ios::ate);
  if (!in) throw MapError("cannot open map file '" + path + "'");
  const std::streamoff size = in.tellg();
  if (size < 0) throw MapError("cannot read map file '" + path + "'");
  if (static_cast<std::size_t>(size) >= max_bytes) {
    throw MapError("'" + path + "' is " + std::to_string(size) + " bytes, limit " +
                   std::to_string(max_bytes));
  }
  std::vector<std::uint8_t> bytes(static_cast<std::size_t>(size));
  in.seekg(0);
  if (!in.read(reinterpret_cast<char*>(bytes.data()), size)) {
    throw MapError("cannot read map file '" + path + "'");
  }
  return bytes;
}

Encoding file_encoding(const std::string& path) {
  if (ends_with(path, ".ot")) return Encoding::kOctomapOt;
  if (!ends_with(path, ".bt")) throw MapError("'" + path + "': unsupported map format (expected .bt or .ot)");
  return Encoding::kOctomapBt;
}

}  // namespace

std::unique_ptr<octomap::OcTree> read_octree_file(const std::string& path) {
  const Encoding encoding = file_encoding(path);
  // Files go through the same validation as wire payloads: OctoMap never parses unchecked bytes.
  const DecodeLimits limits;
  DecodeResult result = decode_map(read_bytes(path, limits.max_bytes), encoding, limits);
  if (!result.ok()) throw MapError("'" + path + "': " + result.reason);
  return std::move(result.tree);
}

std::shared_ptr<const HeldMap> read_map_file(const std::string& path) {
  const Encoding encoding = file_encoding(path);
  const DecodeLimits limits;
  const std::vector<std::uint8_t> bytes = read_bytes(path, limits.max_bytes);
  CheckedMap checked = check_map(bytes.data(), bytes.size(), encoding, limits);
  if (!checked.ok()) throw MapError("'" + path + "': " + checked.reason);
  if (checked.map) return std::move(checked.map);
  // An empty map: the tree decode_map() gives (its resolution, no nodes).
  DecodeResult empty = decode_map(bytes, encoding, limits);
  if (!empty.ok()) throw MapError("'" + path + "': " + empty.reason);
  return std::make_shared<const HeldMap>(std::shared_ptr<const octomap::OcTree>(std::move(empty.tree)));
}

bool is_ot_path(const std::string& path) { return ends_with(path, ".ot"); }

void write_octree_file(const octomap::OcTree& tree, const std::string& path) {
  std::ofstream out(path, std::ios::binary);
  const bool full = is_ot_path(path);
  if (!out || !(full ? tree.write(out) : tree.writeBinaryConst(out))) {
    throw MapError("cannot write map file '" + path + "'");
  }
}

void write_bt_file(const std::vector<std::uint8_t>& bt, const std::string& path) {
  std::ofstream out(path, std::ios::binary);
  out.write(reinterpret_cast<const char*>(bt.data()), static_cast<std::streamsize>(bt.size()));
  out.close();
  if (!out) throw MapError("cannot write map file '" + path + "'");
}

}  // namespace mapmerge
