#include "mapmerge/server/export.hpp"

#include <algorithm>

#include "mapmerge/map/global_fusion.hpp"
#include "mapmerge/map/map_io.hpp"
#include "mapmerge/server/merge_ops.hpp"
#include "mapmerge/server/store.hpp"

namespace mapmerge::server {
namespace {

/// The global map's payload as `.bt` bytes (decoded and re-encoded when stored otherwise).
std::vector<std::uint8_t> as_bt(const GlobalMapOut& g, const DecodeLimits& limits) {
  if (g.encoding == to_string(Encoding::kOctomapBt)) return g.data;
  DecodeResult d = decode_map(g.data, g.encoding, limits);
  if (!d.ok()) throw StoreError("stored global map cannot be decoded: " + d.reason);
  return encode_map(*d.tree, Encoding::kOctomapBt);
}

}  // namespace

ExportedGlobal export_global(const ServerConfig& config, const std::string& prefix) {
  Store store(config.store);
  const StoreSnapshot snap = store.load();
  if (!snap.global) throw StoreError("no global map in " + store.path() + " yet");
  const GlobalMapOut& g = *snap.global;
  std::vector<std::shared_ptr<const octomap::OcTree>> trees;  // keeps the maps alive
  std::vector<NamedMap> maps;
  for (const Contribution& c : g.contributors) {
    const auto m = std::find_if(snap.maps.begin(), snap.maps.end(), [&](const MapSample& s) { return s.robot_id == c.robot_id; });
    const auto p = std::find_if(snap.poses.begin(), snap.poses.end(), [&](const PoseOut& s) { return s.robot_id == c.robot_id; });
    if (m == snap.maps.end() || p == snap.poses.end() || p->state != PoseState::kAligned) continue;
    const DecodedMap decoded = decode_sample(*m, config.limits);
    if (!decoded.map) continue;
    trees.push_back(decoded.map->tree());
    maps.push_back(NamedMap{c.robot_id, trees.back().get(), p->T_global_robot});
  }
  const Provenance provenance = provenance_of(maps, g.resolution);
  write_bt_file(as_bt(g, config.limits), prefix + ".bt");
  write_provenance(provenance, prefix + ".prov");
  return ExportedGlobal{g.version, provenance.robots.size(), provenance.owner.size()};
}

}  // namespace mapmerge::server
