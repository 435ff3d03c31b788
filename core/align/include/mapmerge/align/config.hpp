#pragma once
/// Settings of every stage of the alignment pipeline (issue 3). Plain structs, one per stage.
///
/// Lengths come in three units, so that the same defaults serve maps at 2 cm, 5 cm and 20 cm:
///  - "x res": the map resolution, floored at scale.accuracy_unit (validation, the last ICP
///    iterations and the ground plane work at voxel level, but not finer than two robots'
///    surfaces can agree);
///  - "x u": the feature unit u = max(scale.feature_unit, res / describe.voxel_size), i.e. a
///    fixed metric length (5 cm by default) that grows with coarse maps only so far that the
///    describe cloud keeps at least one voxel per leaf (keypoints, descriptors, matching,
///    submodel blocks); the preprocess lengths use max(scale.feature_unit, res / preprocess.voxel_size);
///  - "x max(u, res)": the refine search lengths (crop margin, NDT).
/// At 5 cm all three are the resolution. Absolute units are named where they are used.

#include <cstddef>
#include <limits>
#include <stdexcept>
#include <string>

namespace mapmerge::align {

/// The metric scale of the features (see the units above).
struct ScaleConfig {
  double feature_unit = 0.05;  ///< u before flooring [m]; 0 = the map resolution (every length scales with it)
  /// Floor of the "x res" unit [m]: a grid finer than this (RGB-D maps at 2 cm) does not make two
  /// robots' surfaces agree more closely than their sensors' noise (RGB-D depth: 1-3 cm at
  /// 2-4 m) and their own drift; 0 = the map resolution.
  double accuracy_unit = 0.05;
};

/// Stage 1: octree -> occupied points.
struct ToPointsConfig {
  double min_occupancy = 0.0;  ///< extra floor on a leaf's occupancy probability [0..1]; 0 = the tree's own threshold only
  std::size_t max_points = 20'000'000;  ///< refuse maps whose expanded occupied voxels exceed this [points]
};

/// Stage 2: pass-through, voxel grid, statistical outlier removal; and the ground, which only
/// keypoints and descriptors (stages 4-5) do without.
struct PreprocessConfig {
  bool pass_through = false;  ///< keep only points with z in [z_min, z_max]
  double z_min = -std::numeric_limits<double>::infinity();  ///< pass-through lower limit [m, map frame]
  double z_max = std::numeric_limits<double>::infinity();   ///< pass-through upper limit [m, map frame]
  bool remove_ground = false;      ///< leave the dominant near-horizontal plane out of keypoints and descriptors (the paper: ground has no features); ICP and validation keep it
  double ground_distance = 1.5;    ///< plane inlier distance [x res]
  double ground_max_tilt_deg = 10.0;  ///< largest angle between plane normal and z for a ground plane [deg]
  double voxel_size = 2.5;         ///< voxel-grid leaf of the cloud used by ICP [x u, at least 1 res]
  bool outlier_removal = true;     ///< statistical outlier removal on/off
  int outlier_mean_k = 8;          ///< neighbours for the statistical outlier removal [points]
  double outlier_stddev = 3.0;     ///< rejection threshold [standard deviations of the mean distance]
  double normal_radius = 6.0;      ///< radius of the ICP cloud's normals while candidates are refined [x u of the preprocess lengths]
  double fine_normal_radius = 3.0;  ///< ... in the final pass on the chosen transform and in refine() [same unit] (1.2 cells of that cloud: planes that follow a coarse map's staircases instead of averaging across them)
  bool orient_normals_to_free = true;  ///< flip normals towards the octree's known free space
};

/// Stage 3: model extraction (submodels) from the source map.
struct SubmodelConfig {
  bool enabled = false;          ///< true: divide the source into blocks (the paper's *_DIV); false: whole map
  double block_size = 100.0;     ///< block edge in x and y [x u] (5 m; the paper: 3 m with denser keypoints)
  bool grid_3d = false;          ///< divide along z as well (multi-level maps)
  double block_height = 60.0;    ///< block edge in z when grid_3d [x u]
  double block_overlap = 0.5;    ///< share of a block shared with its neighbour [0..0.9]
  std::size_t min_keypoints = 8;   ///< blocks with fewer source keypoints are skipped [points]
  bool early_stop = true;        ///< stop launching blocks once a hypothesis is good enough
  double early_stop_inlier_share = 0.8;  ///< inliers / (inliers + contradictions) that counts as good enough [0..1]
  int threads = 0;               ///< worker threads for blocks (0 = TBB default)
};

/// Stage 4: ISS keypoints (Eq. 1-3).
struct KeypointConfig {
  double salient_radius = 10.0;   ///< support radius of the scatter matrix [x u]
  double non_max_radius = 5.0;   ///< non-maximum suppression radius [x u] (8 found a correct hypothesis in 3 of 12 rooms at 10 % overlap, 5 in 11; bench/results)
  double gamma_21 = 0.975;       ///< upper bound on lambda2/lambda1 (largest first, PCL convention) [ratio]
  double gamma_32 = 0.975;       ///< upper bound on lambda3/lambda2 [ratio]
  int min_neighbors = 5;         ///< minimum support size [points]
  int threads = 1;               ///< OpenMP threads inside ISS
};

enum class Descriptor { kFpfh, kShot };

/// Stages 4-5 run on a coarser copy of the preprocessed cloud; stage 5: local descriptors.
struct DescribeConfig {
  double voxel_size = 4.0;       ///< voxel-grid leaf of the cloud keypoints and descriptors use [x u, at least 1 res]
  double normal_radius = 10.0;   ///< normal estimation radius on that cloud [x u]
  Descriptor method = Descriptor::kFpfh;  ///< FPFH (33 bins) or SHOT (352 bins, the paper's)
  double radius = 14.0;          ///< descriptor support radius [x u]
  int threads = 1;               ///< OpenMP threads inside the descriptor estimation
};

enum class MatchMethod { kRansac, kSacIa, kPrerejective, kGcc };

/// Stage 6: correspondences and global hypotheses.
struct MatchConfig {
  MatchMethod method = MatchMethod::kRansac;  ///< kRansac: prerejective RANSAC on feature correspondences (fast);
                                              ///< kSacIa / kPrerejective: PCL's SAC-IA / SampleConsensusPrerejective; kGcc: geometric consistency
  int k_nearest = 3;             ///< target candidates per source keypoint in descriptor space [count]
  bool mutual = false;           ///< keep only mutual nearest neighbours (then k_nearest = 1)
  std::size_t max_correspondences = 3000;  ///< cap, best descriptor distance first [count]
  int iterations = 20000;       ///< RANSAC / SAC-IA / prerejective iterations [count]
  std::size_t seed_pairs = 64;  ///< kRansac: correspondence pairs with the most common compatible partners that seed hypotheses deterministically before the random draws (0 = off) [count]
  double edge_similarity = 0.9;  ///< prerejection: edge-length ratio of sampled triangles [0..1]
  double min_edge = 6.0;         ///< sampled keypoints at least this far apart [x u]
  double inlier_distance = 5.0;  ///< correspondence inlier distance for hypothesis scoring [x u]
  std::size_t min_consensus = 5;  ///< a hypothesis needs this many consistent correspondences [count]
  std::size_t max_hypotheses = 24;  ///< distinct hypotheses kept per submodel [count]
  double gc_size = 4.0;          ///< GCC consensus set resolution [x u]
  int gc_threshold = 5;          ///< GCC minimum cluster size [correspondences]
};

/// Stage 7: hypothesis validation (Eq. 6-8) plus octree contradiction checks.
struct ValidateConfig {
  double d_th = 2.0;             ///< pair distance counted in the fitness, Eq. 7 [x res]
  /// Candidates are ranked by their pairs within d_th capped at this [m], never below one voxel
  /// (the fitness and its limits keep d_th); 0 = no cap. Two robots' maps of one surface agree
  /// within their sensors' noise and one voxel of grid: at 20 cm, ranking by pairs within 2 res
  /// (0.4 m) preferred transforms a metre off in a furnished room, which find partners for more
  /// points than the truth (bench/results/README.md, session 27). 0.1 m is 2 res at 5 cm, so
  /// nothing changes at 5 cm and finer.
  double max_pair_distance = 0.1;
  std::size_t n_th = 100;        ///< fewest pairs for a finite fitness, Eq. 8 [count]
  double min_inlier_fraction = 0.03;  ///< inliers / points of the smaller map, floor [0..1]
  double max_fitness = 0.75;     ///< accepted only if the fitness is below [x res]
  double conflict_distance = 3.0;  ///< a point further than this from any occupied point and inside
                                   ///< the other map's known free space contradicts the transform [x res]
  double min_inlier_share = 0.98;  ///< inliers / (inliers + contradictions) to accept [0..1]
  /// Near conflicts: pairs within d_th but beyond the ranking distance (max_pair_distance, not
  /// below a voxel) whose point lies in the other map's known free space. Quantisation keeps two
  /// maps of one surface within a voxel, so on coarse grids these are misfit: a 20 cm room slid
  /// 0.4 m along its overlap finds more partners within a voxel than the truth, and ~9 % of its
  /// pairs are near conflicts (the truth's: 1 %). Refused above this share of the inliers; they
  /// also count against the ranking like contradictions. At 5 cm and finer the ranking distance
  /// is d_th itself and there are none (bench/results/README.md, session 28). [0..1]; 1 = off.
  double max_near_conflict_share = 0.06;
  double conflict_weight = 5.0;  ///< ranking score = close pairs (max_pair_distance) - conflict_weight * (contradictions + near conflicts) [ratio]
  /// Largest angle between the two maps' z axes under a transform [deg]; 180 = any turn. A
  /// robot's map frame has z up (REP 105; SLAM with an IMU, octomap_server), so two maps of
  /// ground robots differ in tilt by a few degrees at most. Without this bound a 20 cm pair at
  /// 10 % overlap was once merged laid on its side (a 90 deg roll that put walls on the floor:
  /// fitness 0.74 res, inlier share 0.993), and such hypotheses took the refinement slots from
  /// upright ones (bench/results/README.md, session 26).
  double max_tilt_deg = 30.0;
  double ambiguity_ratio = 0.85;  ///< reject when a distinct hypothesis that free space does not contradict scores at least this share of the best that passes [0..1]
  double distinct_rotation_deg = 5.0;  ///< hypotheses differing more than this are distinct [deg]
  double distinct_translation = 10.0;  ///< ... or more than this [x u]
  std::size_t coarse_points = 1500;  ///< points per direction for the quick check of raw hypotheses (twice as many for the final check) [count]
  std::size_t refine_candidates = 3;  ///< best raw hypotheses refined and strictly validated [count]
  double refine_score_ratio = 0.4;  ///< raw hypotheses scoring below this share of the best are not refined [0..1]
};

enum class RefineMethod { kIcp, kOicp, kNdt, kNone };

/// Stage 8: local alignment on the target cropped to the source box inflated by d_m.
struct RefineConfig {
  RefineMethod method = RefineMethod::kOicp;  ///< ICP, occupancy-weighted ICP, NDT, or none
  bool point_to_plane = true;    ///< ICP/OICP objective: point-to-plane (else point-to-point)
  int max_iterations = 30;       ///< ICP/NDT iterations on each candidate [count]
  /// ICP iterations of the final pass on the chosen transform (and of refine()) [count]. Point-to-
  /// plane ICP slides slowly along a narrow overlap: at 30, three of six 15 % cases on the 2 cm
  /// grid ended 5-7 cm off where ICP from the truth ends 1-4 cm off (bench/results/README.md,
  /// session 22).
  int final_iterations = 60;
  /// ICP pair distance, first iteration [x u], at least twice the last (final_correspondence).
  /// Pairs are gated on their plane distance, so source points that far past the end of the
  /// target's surfaces pair with its edges and pull toward more overlap: at 4 x max(u, res)
  /// (0.8 m at 20 cm) ICP from the true transform slid 0.65 m at 10 % overlap (session 27).
  double max_correspondence = 4.0;
  double final_correspondence = 1.0;  ///< ICP pair distance reached by the last iterations [x res] (2 let coarse corridors slide 1.5 voxels)
  double crop_margin = 10.0;     ///< d_m: inflation of the source box when cropping the target [x max(u, res)]
  double convergence_translation = 0.05;  ///< stop when an update moves less than this [x res]
  double convergence_rotation_deg = 0.02;  ///< ... and rotates less than this [deg]
  std::size_t max_points = 3000;  ///< source points in the overlap used by ICP on each candidate [count]
  std::size_t final_points = 10000;  ///< ... by the final pass on the chosen transform (and by refine()) [count]
  /// Restarts of the final pass from its result turned by +-restart_deg about each axis, when
  /// its fitness is above restart_fitness: a narrow overlap can leave ICP in a local minimum a
  /// few degrees off whose fit is visibly looser than a true alignment's (~0.5 voxel: two grids'
  /// centres). The restart with the closest fit that still validates wins. 0 = off [deg]
  double restart_deg = 3.0;
  double restart_fitness = 0.6;  ///< ... above this fitness [x the coarser map's own resolution, not floored]
  double ndt_resolution = 8.0;   ///< NDT cell size [x max(u, res)]
  double ndt_step = 4.0;         ///< NDT More-Thuente step size [x max(u, res)]
};

/// A second global search, on denser features, when the first finds no hypothesis that passes
/// validation. Not when the first was refused as ambiguous: two distinct transforms that both fit
/// are a symmetry, which more features do not make safe. At a narrow overlap (fr_078_tidyup at
/// 10 %: a 1.4 m strip, narrower than two descriptor radii) few keypoints lie in the strip and
/// the first search can miss the truth; a describe cloud of 2.5 u with ISS suppression over 4 u
/// found it in 36 of 36 such cases (the defaults: 24 of 36) at ~3.5x the time, so it runs only
/// after a failed search, where it adds that cost (bench/results/README.md, "Rescue").
struct RescueConfig {
  bool enabled = true;
  double describe_voxel_size = 2.5;  ///< describe.voxel_size of the second search [x u, at least 1 res]
  double non_max_radius = 4.0;       ///< keypoints.non_max_radius of the second search [x u]
};

/// Every stage's settings. `load_align_config` reads it from YAML; `dump_*` write it.
struct AlignConfig {
  ScaleConfig scale;
  ToPointsConfig points;
  PreprocessConfig preprocess;
  SubmodelConfig submodels;
  KeypointConfig keypoints;
  DescribeConfig describe;
  MatchConfig match;
  ValidateConfig validate;
  RefineConfig refine;
  RescueConfig rescue;
  unsigned seed = 42;            ///< random seed of the sample-consensus stages
};

/// Error in a configuration file (unknown key, wrong type, bad value): clear message.
class ConfigError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

/// Reads a YAML file whose sections mirror AlignConfig (`preprocess: {voxel_size: 3}`); keys not
/// given keep their defaults; unknown keys or bad values throw ConfigError.
AlignConfig load_align_config(const std::string& yaml_path);
/// Same from YAML text; keys not given keep `base`'s values (default: AlignConfig's own).
AlignConfig parse_align_config(const std::string& yaml_text, const AlignConfig& base = AlignConfig{});
/// Throws ConfigError when a value is out of its range.
void check_align_config(const AlignConfig& config);
std::string dump_align_config_yaml(const AlignConfig& config);
std::string dump_align_config_json(const AlignConfig& config);

/// The length units of a map (or pair) at resolution `res` [m] under `config` (see the top).
struct LengthUnits {
  double res = 0.0;         ///< the map resolution (grid steps) [m]
  double tolerance = 0.0;   ///< "x res": max(res, scale.accuracy_unit) [m]
  double preprocess = 0.0;  ///< unit of preprocess.voxel_size and normal_radius [m]
  double feature = 0.0;     ///< "x u" [m]
  double refine = 0.0;      ///< "x max(u, res)" [m]
};
LengthUnits length_units(double res, const AlignConfig& config);

const char* to_string(Descriptor d);
const char* to_string(MatchMethod m);
const char* to_string(RefineMethod m);

}  // namespace mapmerge::align
