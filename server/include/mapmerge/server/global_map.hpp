#pragma once
/// The published state, computed from the registry: the fused global map of every aligned
/// robot, and one pose per robot (aligned ones with T_global_robot, the others unknown).

#include <cstdint>
#include <optional>
#include <vector>

#include "mapmerge/server/config.hpp"
#include "mapmerge/server/messages.hpp"
#include "mapmerge/server/registry.hpp"

namespace mapmerge::server {

/// Fuses the aligned robots' maps (nothing when no robot is aligned).
std::optional<GlobalMapOut> build_global_map(const Registry& registry, const ServerConfig& config,
                                             std::uint64_t version);

/// One pose per robot known to the registry.
std::vector<PoseOut> pose_outputs(const Registry& registry);

}  // namespace mapmerge::server
