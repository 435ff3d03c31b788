#pragma once
/// Map alignment (issue 3): find T_target_source between two OctoMaps.
///
///   prepare_map(tree)  once per robot map: points, filtered cloud, keypoints, descriptors
///   align(t, s)        global search (no initial guess), validated; used once per pair
///   refine(t, s, T0)   local only, from a known transform; used when a map grows
///
/// "No alignment" is a value (AlignResult::accepted == false with a reason), never an exception.

#include <cstddef>
#include <functional>
#include <limits>
#include <memory>
#include <string>

#include <Eigen/Core>
#include <octomap/OcTree.h>

#include "mapmerge/align/config.hpp"

namespace mapmerge {
class HeldMap;
}

namespace mapmerge::align {

/// Wall time of each stage [ms]. Preparation stages add up both maps' times.
struct StageTimings {
  double to_points_ms = 0.0;
  double preprocess_ms = 0.0;
  double keypoints_ms = 0.0;
  double describe_ms = 0.0;
  double submodels_ms = 0.0;  ///< block extraction and all blocks' hypothesis generation
  double match_ms = 0.0;      ///< descriptor correspondences
  double validate_ms = 0.0;
  double refine_ms = 0.0;
  double total_ms = 0.0;      ///< wall time of the whole call
};

/// Quality of one transform, as measured by the validation stage.
struct Validation {
  double fitness = std::numeric_limits<double>::infinity();  ///< Eq. 6 [m]; +inf if fewer than n_th pairs
  std::size_t inliers = 0;      ///< n_w of Eq. 8, both directions [count]
  std::size_t close_pairs = 0;  ///< of those, pairs within the ranking distance (ValidateConfig::max_pair_distance) [count]
  std::size_t conflicts = 0;    ///< points landing in the other map's known free space [count]
  std::size_t near_conflicts = 0;  ///< pairs within d_th but beyond the ranking distance whose point lies in the other map's known free space [count]
  std::size_t checked = 0;      ///< points tested, both directions [count]
  double overlap = 0.0;         ///< (inliers + conflicts) / checked: share seen by both maps [0..1]
  double inlier_share = 0.0;    ///< inliers / (inliers + conflicts) [0..1]
  double inlier_fraction = 0.0;  ///< inliers / checked [0..1]
  double near_conflict_share = 0.0;  ///< near_conflicts / inliers [0..1]
  double tilt_deg = 0.0;        ///< angle between the target's z axis and the source's under the transform [deg]
};

struct AlignResult {
  bool accepted = false;        ///< a transform passed validation
  Eigen::Matrix4d T_target_source = Eigen::Matrix4d::Identity();  ///< maps source points into the target frame
  double fitness = std::numeric_limits<double>::infinity();  ///< Eq. 6 of the final transform [m]
  std::size_t inliers = 0;      ///< pairs closer than d_th [count]
  double overlap = 0.0;         ///< estimated share of points seen by both maps [0..1]
  double inlier_share = 0.0;    ///< inliers / (inliers + contradictions) [0..1]
  int submodel = -1;            ///< winning block in spiral order; -1 whole map / none
  std::size_t hypotheses = 0;   ///< raw hypotheses generated [count] (both searches' when rescued)
  bool rescued = false;         ///< the first search found nothing acceptable and a second, on denser features (AlignConfig::rescue), ran
  std::string reason;           ///< why not accepted (empty when accepted)
  StageTimings timings;
};

/// One map made ready for alignment: owns its points, filtered cloud, keypoints, descriptors
/// and a copy of the octree (free space for the contradiction test). Cheap to copy (shared),
/// immutable, safe to use from several threads.
class PreparedMap {
 public:
  struct Impl;
  PreparedMap();
  explicit PreparedMap(std::shared_ptr<const Impl> impl);
  double resolution() const;
  std::size_t num_points() const;     ///< occupied voxels (stage 1) [count]
  std::size_t num_filtered() const;   ///< after preprocessing [count]
  std::size_t num_keypoints() const;  ///< with a valid descriptor [count]; 0 without features
  bool has_features() const;          ///< keypoints and descriptors (stages 4, 5): usable by align()
  const StageTimings& timings() const;  ///< stages 1, 2, 4, 5 of this map
  const Impl& impl() const;
  bool empty() const { return impl_ == nullptr; }

 private:
  std::shared_ptr<const Impl> impl_;
};

/// Stages 1, 2, 4, 5 for one map. Throws std::invalid_argument for an unusable map (no
/// occupied voxel) or config. The prepared map keeps no reference to the tree: what validation
/// asks of its free space is kept as the tree's free leaves (mapmerge::LeafSet, ~8 B each).
PreparedMap prepare_map(const octomap::OcTree& tree, const AlignConfig& config);

/// Stages 1 and 2 only (no keypoints, no descriptors): all refine() and validate() read, at a
/// fraction of prepare_map()'s time and memory; align() refuses such a map (not accepted).
PreparedMap prepare_for_refine(const octomap::OcTree& tree, const AlignConfig& config);

/// prepare_map() and prepare_for_refine() of a held map, read off its binary body: its octree is
/// not built (~57 B a node, and the time to build it), the result is the same as from tree().
PreparedMap prepare_map(const HeldMap& map, const AlignConfig& config);
PreparedMap prepare_for_refine(const HeldMap& map, const AlignConfig& config);

/// Asked between a global search's steps (blocks, candidates, the rescue's feature builds): once
/// it returns true the search stops and returns not accepted, reason "cancelled". For a caller
/// that must not wait for a whole search (a server shutting down, a map replaced meanwhile).
using Cancel = std::function<bool()>;

/// Global search: stages 3, 6, 7, 8. Never throws for "no alignment".
AlignResult align(const PreparedMap& target, const PreparedMap& source, const AlignConfig& config,
                  const Cancel& cancel = {});

/// The rescue's search alone (AlignConfig::rescue's denser features, whether or not
/// rescue.enabled), for a pair that align() without the rescue refused: to be run later, when
/// there is time to spare (the server's idle work). Sets `rescued`; never throws for "no
/// alignment". Its timings are this search's only.
AlignResult rescue(const PreparedMap& target, const PreparedMap& source, const AlignConfig& config,
                   const Cancel& cancel = {});
/// Whether a refusal's reason says two distinct transforms fit almost equally: align() gives
/// such a pair no second search (more features would only pick one side of a symmetry).
bool ambiguous_refusal(const std::string& reason);
/// Local only: stage 8 from T_target_source_init, then stage 7 on the result.
AlignResult refine(const PreparedMap& target, const PreparedMap& source,
                   const Eigen::Matrix4d& T_target_source_init, const AlignConfig& config);

/// Validation of a given transform (stage 7) without changing it.
Validation validate(const PreparedMap& target, const PreparedMap& source,
                    const Eigen::Matrix4d& T_target_source, const AlignConfig& config);

/// prepare_map for both (in parallel) then align.
AlignResult align_maps(const octomap::OcTree& target, const octomap::OcTree& source,
                       const AlignConfig& config);
/// The same, both prepared off their bytes (no octree is built).
AlignResult align_maps(const HeldMap& target, const HeldMap& source, const AlignConfig& config);

/// JSON object of the stage timings, e.g. {"to_points_ms": 3.1, ...}.
std::string timings_json(const StageTimings& t);

}  // namespace mapmerge::align
