#pragma once
// Helpers shared by the tests of core/map: the real maps of data/ as bytes and trees.

#include <cstdint>
#include <fstream>
#include <iterator>
#include <memory>
#include <string>
#include <vector>

#include <octomap/OcTree.h>

#include "mapmerge/map/map_io.hpp"

namespace mapmerge::test {

inline std::string data_path(const std::string& name) {
  return std::string(MAPMERGE_DATA_DIR) + "/" + name;
}

inline std::vector<std::uint8_t> file_bytes(const std::string& name) {
  std::ifstream in(data_path(name), std::ios::binary);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

inline std::unique_ptr<octomap::OcTree> load(const std::string& name) {
  return read_octree_file(data_path(name));
}

inline std::string as_string(const std::vector<std::uint8_t>& bytes) {
  return {bytes.begin(), bytes.end()};
}

inline std::vector<std::uint8_t> as_bytes(const std::string& text) {
  return {text.begin(), text.end()};
}

/// Offset of the first body byte of a `.bt`/`.ot` file (just after the "data" line).
inline std::size_t body_offset(const std::vector<std::uint8_t>& bytes) {
  const std::string text = as_string(bytes);
  return text.find("\ndata\n") + 6;
}

}  // namespace mapmerge::test
