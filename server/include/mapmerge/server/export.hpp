#pragma once
/// `mapmerge-server --state-dir DIR --export-global PREFIX`: the last published global map and
/// its per-robot provenance, read from the state store (the server may keep running: SQLite WAL).

#include <cstddef>
#include <string>

#include "mapmerge/server/config.hpp"

namespace mapmerge::server {

/// What export_global() wrote.
struct ExportedGlobal {
  std::uint64_t version = 0;     ///< global map version
  std::size_t robots = 0;        ///< robots in the provenance (the map's contributors)
  std::size_t owned_voxels = 0;  ///< voxels with a contributing robot
};

/// Writes PREFIX.bt (the last published global map, `.bt`) and PREFIX.prov (which robot
/// contributed each occupied voxel, and each robot's published pose; core/map provenance file,
/// read by `mapmerge render PREFIX.bt --by-robot PREFIX.prov`). Provenance comes from each
/// contributor's stored map at its published pose. Throws StoreError when the store cannot be
/// read or holds no global map, MapError when a file cannot be written.
ExportedGlobal export_global(const ServerConfig& config, const std::string& prefix);

}  // namespace mapmerge::server
