#pragma once
/// The pipeline's stages as plain functions on Eigen/octomap types (no PCL), for tests, the
/// bench and callers that need a single stage. align.hpp chains them.

#include <cstddef>
#include <vector>

#include <Eigen/Core>
#include <octomap/OcTree.h>

#include "mapmerge/align/config.hpp"

namespace mapmerge {
class HeldMap;
}

namespace mapmerge::align {

/// One occupied voxel centre with its occupancy probability.
struct OccupiedPoint {
  Eigen::Vector3f position;  ///< voxel centre [m, map frame]
  float occupancy = 0.5F;    ///< occupancy probability [0..1]
};

/// Stage 1: centres of all occupied voxels at full resolution (pruned leaves expanded).
/// Throws std::invalid_argument when the expansion would exceed config.max_points.
std::vector<OccupiedPoint> to_points(const octomap::OcTree& tree, const ToPointsConfig& config);
/// Stage 1 off a map's binary body (its octree is not built): the same points, in the same
/// order, as to_points(*map.tree()); a map without a body is read off its tree.
std::vector<OccupiedPoint> to_points(const HeldMap& map, const ToPointsConfig& config);

/// Stage 2's ground on a bare point set: indices of the points that preprocess.remove_ground
/// leaves out of keypoints and descriptors (the pipeline asks this of its preprocessed cloud);
/// empty when there is no near-horizontal plane, or more than a quarter of the points lie below
/// it: a ceiling or a table top is no ground.
/// `unit`: the "x res" unit of ground_distance [m] (length_units(res, config).tolerance).
std::vector<std::size_t> ground_points(const std::vector<Eigen::Vector3f>& points,
                                       const PreprocessConfig& config, double unit);

/// One submodel: a box of the source map and the indices of the points inside.
struct Block {
  Eigen::Vector3f min;                ///< lower corner [m]
  Eigen::Vector3f max;                ///< upper corner [m]
  std::vector<std::size_t> members;   ///< indices into the input points
};

/// Stage 3: blocks of `block_size` on a 2D (or 3D) grid over the points' bounding box, in
/// spiral order from the border inwards. Empty blocks are dropped. `unit`: the feature unit
/// u of the block lengths [m] (length_units(res, config).feature).
std::vector<Block> make_submodels(const std::vector<Eigen::Vector3f>& points,
                                  const SubmodelConfig& config, double unit);

/// Stage 4 on a bare point set: indices of the ISS keypoints (Eq. 1-3); radii in units of
/// `unit` [m].
std::vector<std::size_t> iss_keypoints(const std::vector<Eigen::Vector3f>& points,
                                       const KeypointConfig& config, double unit);

/// Eq. 6-8 on pair distances: mean of the distances <= d_th; +inf when fewer than n_th.
struct Fitness {
  double value = 0.0;   ///< [m] or +inf
  std::size_t n_w = 0;  ///< pairs within d_th [count]
};
Fitness fitness_from_distances(const std::vector<double>& pair_distances, double d_th,
                               std::size_t n_th);

/// Eq. 6-8 with nearest-neighbour pairs: for each point of `source_in_target` its nearest
/// point of `target`.
Fitness fitness_score(const std::vector<Eigen::Vector3f>& source_in_target,
                      const std::vector<Eigen::Vector3f>& target, double d_th, std::size_t n_th);

}  // namespace mapmerge::align
