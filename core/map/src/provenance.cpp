#include "mapmerge/map/provenance.hpp"

#include <cstring>
#include <fstream>
#include <iterator>

#include "mapmerge/map/map_io.hpp"

namespace mapmerge {
namespace {

constexpr char kMagic[8] = {'M', 'M', 'P', 'R', 'O', 'V', '1', '\n'};

template <typename T>
void put(std::ofstream& out, const T& value) {
  out.write(reinterpret_cast<const char*>(&value), sizeof(T));
}

/// Reads little-endian values from a byte buffer, failing cleanly at its end.
class Reader {
 public:
  Reader(const std::vector<char>& bytes, const std::string& path) : bytes_(bytes), path_(path) {}
  template <typename T>
  T get() {
    T value{};
    need(sizeof(T));
    std::memcpy(&value, bytes_.data() + pos_, sizeof(T));
    pos_ += sizeof(T);
    return value;
  }
  std::string get_string(std::size_t n) {
    need(n);
    std::string s(bytes_.data() + pos_, n);
    pos_ += n;
    return s;
  }
  void need(std::size_t n) const {
    if (bytes_.size() - pos_ < n) throw MapError("'" + path_ + "': provenance file is truncated");
  }
  std::size_t left() const { return bytes_.size() - pos_; }

 private:
  const std::vector<char>& bytes_;
  const std::string& path_;
  std::size_t pos_ = 0;
};

}  // namespace

void write_provenance(const Provenance& provenance, const std::string& path) {
  std::ofstream out(path, std::ios::binary);
  if (!out) throw MapError("cannot write provenance file '" + path + "'");
  out.write(kMagic, sizeof(kMagic));
  put(out, provenance.resolution);
  put(out, static_cast<std::uint32_t>(provenance.robots.size()));
  for (const RobotFrame& robot : provenance.robots) {
    put(out, static_cast<std::uint16_t>(robot.name.size()));
    out.write(robot.name.data(), static_cast<std::streamsize>(robot.name.size()));
    for (int r = 0; r < 4; ++r) {
      for (int c = 0; c < 4; ++c) put(out, robot.T_global_robot(r, c));
    }
  }
  put(out, static_cast<std::uint64_t>(provenance.owner.size()));
  for (const auto& [key, owner] : provenance.owner) {
    const std::uint16_t record[4] = {key.k[0], key.k[1], key.k[2], owner.robot};
    out.write(reinterpret_cast<const char*>(record), sizeof(record));
  }
  if (!out) throw MapError("cannot write provenance file '" + path + "'");
}

Provenance read_provenance(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw MapError("cannot open provenance file '" + path + "'");
  const std::vector<char> bytes{std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
  if (bytes.size() < sizeof(kMagic) || std::memcmp(bytes.data(), kMagic, sizeof(kMagic)) != 0) {
    throw MapError("'" + path + "' is not a mapmerge provenance file");
  }
  Reader reader(bytes, path);
  reader.get_string(sizeof(kMagic));
  Provenance provenance;
  provenance.resolution = reader.get<double>();
  const auto robots = reader.get<std::uint32_t>();
  if (robots > 65536) throw MapError("'" + path + "': too many robots");
  for (std::uint32_t i = 0; i < robots; ++i) {
    RobotFrame frame;
    frame.name = reader.get_string(reader.get<std::uint16_t>());
    for (int r = 0; r < 4; ++r) {
      for (int c = 0; c < 4; ++c) frame.T_global_robot(r, c) = reader.get<double>();
    }
    provenance.robots.push_back(std::move(frame));
  }
  const auto count = reader.get<std::uint64_t>();
  if (count != reader.left() / 8 || reader.left() % 8 != 0) {
    throw MapError("'" + path + "': provenance record count does not match the file size");
  }
  provenance.owner.reserve(static_cast<std::size_t>(count));
  for (std::uint64_t i = 0; i < count; ++i) {
    const auto x = reader.get<std::uint16_t>();
    const auto y = reader.get<std::uint16_t>();
    const auto z = reader.get<std::uint16_t>();
    const auto robot = reader.get<std::uint16_t>();
    provenance.owner[octomap::OcTreeKey(x, y, z)] = VoxelOwner{robot, 0.0F};
  }
  return provenance;
}

}  // namespace mapmerge
