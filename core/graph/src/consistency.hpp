#pragma once
// Internal: cycle consistency (stage 1). Loops through each active edge are enumerated
// (shortest first, plus the shortest loop of any length as a fallback) and tested against the
// ConsistencyConfig thresholds. Rejection, repeated until every remaining loop closes:
//   1. edges with at least one open loop and no closed one are rejected together (no support);
//   2. otherwise the edge with the largest share of open loops is rejected (ties: more open
//      loops, then the less certain edge).
// Rule 1 means a robot whose loops all disagree loses all of them (it goes back to unknown)
// instead of keeping an arbitrary one: a loop says that one of its edges is wrong, not which.

#include "mapmerge/graph/config.hpp"
#include "work_graph.hpp"

namespace mapmerge::graph::detail {

/// Marks rejected edges inactive and fills every edge's report (state, reason, evidence, loop
/// counts, verified). Rejected edges stay rejected; active edges end with only closed loops.
void check_consistency(WorkGraph& graph, const ConsistencyConfig& config);

}  // namespace mapmerge::graph::detail
