// Stages 1, 2, 4, 5 for one map (PCL translation unit 1 of 3).
#include <chrono>
#include <mutex>
#include <stdexcept>

#include <pcl/console/print.h>
#include <pcl/features/fpfh.h>
#include <pcl/features/fpfh_omp.h>
#include <pcl/features/normal_3d.h>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <pcl/features/shot_omp.h>
#include <pcl/filters/extract_indices.h>
#include <pcl/filters/statistical_outlier_removal.h>
#include <pcl/filters/voxel_grid.h>
#include <pcl/keypoints/iss_3d.h>
#include <pcl/sample_consensus/ransac.h>
#include <pcl/sample_consensus/sac_model_perpendicular_plane.h>
// The templates of PCL's features, filters and sample consensus are instantiated here from
// their implementation headers, not taken from libpcl_features, libpcl_filters and
// libpcl_sample_consensus: those libraries carry ~170k relocations for instantiations the
// pipeline never calls, and loading them cost ~40 ms at every start of `mapmerge`.
#include <pcl/features/impl/boundary.hpp>
#include <pcl/features/impl/fpfh.hpp>
#include <pcl/features/impl/fpfh_omp.hpp>
#include <pcl/features/impl/integral_image_normal.hpp>
#include <pcl/features/impl/normal_3d.hpp>
#include <pcl/features/impl/shot.hpp>
#include <pcl/features/impl/shot_lrf.hpp>
#include <pcl/features/impl/shot_lrf_omp.hpp>
#include <pcl/features/impl/shot_omp.hpp>
#include <pcl/filters/impl/extract_indices.hpp>
#include <pcl/filters/impl/filter_indices.hpp>
#include <pcl/filters/impl/statistical_outlier_removal.hpp>
#include <pcl/filters/impl/voxel_grid.hpp>
#include <pcl/sample_consensus/impl/ransac.hpp>
#include <pcl/sample_consensus/impl/sac_model_perpendicular_plane.hpp>
#include <pcl/sample_consensus/impl/sac_model_plane.hpp>

#include "mapmerge/align/stages.hpp"
#include "mapmerge/map/held_map.hpp"
#include "prepared_map_impl.hpp"

/// FPFH's pair feature for the pipeline's points (the one non-template function the FPFH
/// template calls in libpcl_features). For the pair (p, n_p), (q, n_q): the source is the point
/// whose normal makes the smaller angle with the line joining them; with d the unit vector
/// from the source to the other point and u = the source's normal, v = d x u / |d x u|,
/// w = u x v (the Darboux frame), and n the other point's normal:
///   f1 = atan2(w.n, u.n), f2 = v.n, f3 = u.d, f4 = |q - p|.
/// A pair at one position, or whose line runs along the source's normal, has no frame: all
/// four are 0 and the pair is not counted. Same float operations, in the same order, as
/// PCL's, so the descriptors are the same to the bit.
template <>
bool pcl::FPFHEstimation<mapmerge::align::Point, mapmerge::align::Point, mapmerge::align::Fpfh>::computePairFeatures(
    const pcl::PointCloud<mapmerge::align::Point>& cloud, const pcl::PointCloud<mapmerge::align::Point>& normals,
    int p_idx, int q_idx, float& f1, float& f2, float& f3, float& f4) {
  const auto zero_w = [](Eigen::Vector4f v) {
    v[3] = 0.0F;
    return v;
  };
  Eigen::Vector4f line = zero_w(cloud[q_idx].getVector4fMap() - cloud[p_idx].getVector4fMap());
  f4 = line.norm();
  f1 = f2 = f3 = 0.0F;
  if (f4 == 0.0F) return false;
  Eigen::Vector4f u = zero_w(normals[p_idx].getNormalVector4fMap());
  Eigen::Vector4f n = zero_w(normals[q_idx].getNormalVector4fMap());
  const float cos_p = u.dot(line) / f4;
  const float cos_q = n.dot(line) / f4;
  // acos, as PCL compares: its NaN above 1 (rounding) and its ties decide as there.
  if (std::acos(std::fabs(cos_p)) > std::acos(std::fabs(cos_q))) {
    std::swap(u, n);
    line = -line;
    f3 = -cos_q;
  } else {
    f3 = cos_p;
  }
  Eigen::Vector4f v = zero_w(line.cross3(u));
  const float v_norm = v.norm();
  if (v_norm == 0.0F) {
    f3 = f4 = 0.0F;
    return false;
  }
  v /= v_norm;
  const Eigen::Vector4f w = zero_w(u.cross3(v));
  f2 = v.dot(n);
  f1 = std::atan2(w.dot(n), u.dot(n));
  return true;
}

namespace mapmerge::align {
namespace {

using Clock = std::chrono::steady_clock;
double ms_since(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

/// Stage 1's points as a cloud of `P` (intensity = occupancy; PCL's constructor zeroes a normal).
template <class P>
typename pcl::PointCloud<P>::Ptr to_cloud(const std::vector<OccupiedPoint>& points) {
  auto cloud = std::make_shared<pcl::PointCloud<P>>();
  cloud->reserve(points.size());
  for (const auto& p : points) cloud->push_back(P(p.position.x(), p.position.y(), p.position.z(), p.occupancy));
  return cloud;
}

/// Bare points as a cloud (intensity and normal zero).
Cloud::Ptr bare_cloud(const std::vector<Eigen::Vector3f>& points) {
  auto cloud = std::make_shared<Cloud>();
  cloud->reserve(points.size());
  for (const auto& p : points) cloud->push_back(Point(p.x(), p.y(), p.z(), 0.0F));
  return cloud;
}

/// Indices of the ground: the points within ground_distance of the largest plane whose normal is
/// within ground_max_tilt_deg of z (RANSAC on one thread, so the same cloud gives the same
/// plane), if at most a quarter of the cloud lies below that plane (not a ceiling, not a table
/// top); else none.
pcl::Indices ground_indices(const Cloud::ConstPtr& cloud, const PreprocessConfig& c, double res) {
  auto plane = std::make_shared<pcl::SampleConsensusModelPerpendicularPlane<Point>>(cloud);
  plane->setAxis(Eigen::Vector3f::UnitZ());
  plane->setEpsAngle(c.ground_max_tilt_deg * M_PI / 180.0);
  const double distance = c.ground_distance * res;
  pcl::RandomSampleConsensus<Point> ransac(plane, distance);
  ransac.setMaxIterations(200);
  ransac.setNumberOfThreads(1);
  if (!ransac.computeModel()) return {};
  pcl::Indices inliers;
  ransac.getInliers(inliers);
  Eigen::VectorXf coefficients, refined;
  ransac.getModelCoefficients(coefficients);
  plane->optimizeModelCoefficients(inliers, coefficients, refined);  // least squares on the inliers
  plane->selectWithinDistance(refined, distance, inliers);
  if (inliers.empty() || refined.size() != 4) return {};
  // Below the plane: on the side its normal, turned up, points away from.
  const Eigen::Vector4f up = refined[2] < 0.0F ? Eigen::Vector4f(-refined) : Eigen::Vector4f(refined);
  std::size_t below = 0;
  for (const auto& p : *cloud) below += up.head<3>().dot(p.getVector3fMap()) + up[3] < 0.0F ? 1 : 0;
  if (below > cloud->size() / 4) return {};
  return inliers;
}

Cloud::Ptr remove_ground(const Cloud::Ptr& cloud, const PreprocessConfig& c, double res) {
  const pcl::Indices ground = ground_indices(cloud, c, res);
  if (ground.empty()) return cloud;
  pcl::ExtractIndices<Point> extract;
  extract.setInputCloud(cloud);
  extract.setIndices(std::make_shared<pcl::Indices>(ground));
  extract.setNegative(true);
  auto out = std::make_shared<Cloud>();
  extract.filter(*out);
  return out;
}

Cloud::Ptr voxel_grid(const Cloud::Ptr& cloud, double leaf_size) {
  if (leaf_size <= 0.0) return cloud;
  pcl::VoxelGrid<Point> grid;
  const auto leaf = static_cast<float>(leaf_size);
  grid.setLeafSize(leaf, leaf, leaf);
  grid.setInputCloud(cloud);
  auto out = std::make_shared<Cloud>();
  grid.filter(*out);
  return out;
}

/// Stage 2: pass-through, voxel grid, statistical outlier removal (the ground goes from the
/// describe cloud only: see prepare_stages).
Cloud::Ptr preprocess(const Cloud::Ptr& input, const PreprocessConfig& c, const LengthUnits& units) {
  const double res = units.res;
  Cloud::Ptr cloud = input;
  if (c.pass_through) {
    auto kept = std::make_shared<Cloud>();
    for (const auto& p : *cloud)
      if (p.z >= c.z_min && p.z <= c.z_max) kept->push_back(p);
    cloud = kept;
  }
  const double leaf = c.voxel_size * units.preprocess;
  if (leaf > 1.01 * res) cloud = voxel_grid(cloud, leaf);
  if (c.outlier_removal && cloud->size() > static_cast<std::size_t>(c.outlier_mean_k) + 1) {
    pcl::StatisticalOutlierRemoval<Point> sor;
    sor.setMeanK(c.outlier_mean_k);
    sor.setStddevMulThresh(c.outlier_stddev);
    sor.setInputCloud(cloud);
    auto out = std::make_shared<Cloud>();
    sor.filter(*out);
    cloud = out;
  }
  return cloud;
}

/// Free-space votes along +n and -n: the surface faces the side the sensor saw as free.
int free_votes(const LeafSet& free, const Point& p, float sign, double res) {
  int votes = 0;
  for (int step = 1; step <= 2; ++step) {
    const auto d = static_cast<float>(sign * step * res);
    const Eigen::Vector3f q = p.getVector3fMap() + d * p.getNormalVector3fMap();
    if (free.contains(q.cast<double>())) ++votes;
  }
  return votes;
}

/// ISS keypoints of `cloud`; `tree` indexes `cloud`.
pcl::IndicesPtr detect_iss(const Cloud::ConstPtr& cloud, const SerialKdTree<Point>::Ptr& tree,
                           const KeypointConfig& c, double unit) {
  pcl::ISSKeypoint3D<Point, Point, Point> iss;
  iss.setInputCloud(cloud);
  iss.setSearchMethod(tree);
  iss.setSalientRadius(c.salient_radius * unit);
  iss.setNonMaxRadius(c.non_max_radius * unit);
  iss.setThreshold21(c.gamma_21);
  iss.setThreshold32(c.gamma_32);
  iss.setMinNeighbors(c.min_neighbors);
  iss.setNumberOfThreads(static_cast<unsigned>(std::max(1, c.threads)));
  Cloud keypoints;
  iss.compute(keypoints);
  auto indices = std::make_shared<pcl::Indices>(iss.getKeypointsIndices()->indices);
  return indices;
}

/// Keeps the keypoints whose descriptor is finite; returns their positions.
template <class Feature>
Cloud::Ptr keep_valid(const Cloud& cloud, const pcl::Indices& indices,
                      pcl::PointCloud<Feature>& features) {
  auto keypoints = std::make_shared<Cloud>();
  pcl::PointCloud<Feature> kept;
  for (std::size_t i = 0; i < indices.size(); ++i) {
    const auto& f = features[i];
    bool finite = true;
    if constexpr (std::is_same_v<Feature, Shot>) {
      for (float v : f.descriptor) finite = finite && std::isfinite(v);
      for (float v : f.rf) finite = finite && std::isfinite(v);
    } else {
      for (float v : f.histogram) finite = finite && std::isfinite(v);
    }
    if (!finite) continue;
    keypoints->push_back(cloud[indices[i]]);
    kept.push_back(f);
  }
  features = std::move(kept);
  return keypoints;
}

template <class Estimator, class Features>
void compute_feature(Estimator& est, const Cloud::Ptr& cloud, const SerialKdTree<Point>::Ptr& tree,
                     const pcl::IndicesPtr& indices, double radius, Features& out) {
  est.setInputCloud(cloud);
  est.setIndices(indices);
  est.setInputNormals(cloud);
  est.setSearchMethod(tree);
  est.setRadiusSearch(radius);
  est.compute(out);
}

/// Stage 5 at `indices` of m.coarse; `tree` indexes m.coarse.
void describe(PreparedMap::Impl& m, SerialKdTree<Point>::Ptr tree, pcl::IndicesPtr indices,
              const DescribeConfig& c, double unit) {
  const double radius = c.radius * unit;
  // PCL's FPFH and SHOT read every neighbour's normal. A point without a plane (NaN normal: its
  // neighbours lie on a line, e.g. a pole on a 20 cm grid) gives NaN angles, which PCL casts to a
  // histogram bin: undefined behaviour (UBSan in fpfh.hpp). Such points take no part: they are
  // left out of the described cloud, and a keypoint among them has no descriptor anyway.
  const auto planar = [](const Point& p) { return pcl::isNormalFinite(p); };
  if (!std::all_of(m.coarse->begin(), m.coarse->end(), planar)) {
    auto kept = std::make_shared<Cloud>();
    std::vector<int> new_index(m.coarse->size(), -1);
    for (std::size_t i = 0; i < m.coarse->size(); ++i) {
      if (!planar((*m.coarse)[i])) continue;
      new_index[i] = static_cast<int>(kept->size());
      kept->push_back((*m.coarse)[i]);
    }
    auto kept_indices = std::make_shared<pcl::Indices>();
    for (const auto i : *indices)
      if (new_index[static_cast<std::size_t>(i)] >= 0) kept_indices->push_back(new_index[static_cast<std::size_t>(i)]);
    m.coarse = kept;
    tree = std::make_shared<SerialKdTree<Point>>();
    if (!kept->empty()) tree->setInputCloud(kept);
    indices = kept_indices;
  }
  const unsigned threads = static_cast<unsigned>(std::max(1, c.threads));
  if (c.method == Descriptor::kFpfh) {
    auto features = std::make_shared<pcl::PointCloud<Fpfh>>();
    if (threads > 1) {
      pcl::FPFHEstimationOMP<Point, Point, Fpfh> est(threads);
      compute_feature(est, m.coarse, tree, indices, radius, *features);
    } else {
      pcl::FPFHEstimation<Point, Point, Fpfh> est;  // no OpenMP team to start and spin
      compute_feature(est, m.coarse, tree, indices, radius, *features);
    }
    m.keypoints = keep_valid(*m.coarse, *indices, *features);
    m.fpfh = features;
    m.fpfh_tree = std::make_shared<SerialKdTree<Fpfh>>();
    if (!features->empty()) m.fpfh_tree->setInputCloud(features);
  } else {
    pcl::SHOTEstimationOMP<Point, Point, Shot> est(threads);
    auto features = std::make_shared<pcl::PointCloud<Shot>>();
    compute_feature(est, m.coarse, tree, indices, radius, *features);
    m.keypoints = keep_valid(*m.coarse, *indices, *features);
    m.shot = features;
    m.shot_tree = std::make_shared<SerialKdTree<Shot>>();
    if (!features->empty()) m.shot_tree->setInputCloud(features);
  }
}

}  // namespace

void estimate_normals(Cloud& cloud, const SerialKdTree<Point>& search, double radius, const LeafSet* orient_to,
                      double res) {
  const bool orient = orient_to != nullptr;
  tbb::parallel_for(tbb::blocked_range<std::size_t>(0, cloud.size(), 512), [&](const auto& r) {
    pcl::Indices idx;
    std::vector<float> d2;
    for (std::size_t i = r.begin(); i < r.end(); ++i) {
      Point& p = cloud[i];
      Eigen::Vector4f plane;
      float curvature = 0.0F;
      if (search.radiusSearch(p, radius, idx, d2) < 3 ||
          !pcl::computePointNormal(cloud, idx, plane, curvature)) {
        p.normal_x = p.normal_y = 0.0F;
        p.normal_z = 1.0F;
        p.curvature = 0.0F;
        continue;
      }
      p.getNormalVector3fMap() = plane.head<3>();
      p.curvature = curvature;
      // A degenerate neighbourhood (all points on one line, as along a one-voxel edge of a
      // coarse map) has no plane: PCL gives NaN. The normal stays NaN (descriptors drop such
      // points, ICP skips them) and is not oriented (OctoMap cannot look up a NaN position).
      if (!plane.head<3>().allFinite()) continue;
      const int plus = orient ? free_votes(*orient_to, p, 1.0F, res) : 0;
      const int minus = orient ? free_votes(*orient_to, p, -1.0F, res) : 0;
      const bool flip = minus > plus || (minus == plus && p.normal_z < 0.0F);
      if (flip) p.getNormalVector3fMap() *= -1.0F;
    }
  });
}


PreparedMap::PreparedMap() = default;
PreparedMap::PreparedMap(std::shared_ptr<const Impl> impl) : impl_(std::move(impl)) {}
double PreparedMap::resolution() const { return impl().resolution; }
std::size_t PreparedMap::num_points() const { return impl().num_points; }
std::size_t PreparedMap::num_filtered() const { return impl().cloud->size(); }
std::size_t PreparedMap::num_keypoints() const { return impl().keypoints ? impl().keypoints->size() : 0; }
bool PreparedMap::has_features() const { return impl_ && impl_->keypoints != nullptr; }
const StageTimings& PreparedMap::timings() const { return impl().timings; }
const PreparedMap::Impl& PreparedMap::impl() const {
  if (!impl_) throw std::logic_error("PreparedMap is empty (use prepare_map)");
  return *impl_;
}

namespace {

/// Stages 4-5 (and the describe cloud) on a map whose stage-2 cloud, with broad normals, is
/// ready: the ground left out, the describe cloud, its normals, ISS keypoints and descriptors.
void add_features(PreparedMap::Impl& m, const AlignConfig& config, const LengthUnits& units) {
  auto t0 = Clock::now();
  // The ground has no features (the paper): keypoints and descriptors do without it. ICP keeps
  // it (its target crop: the only surface that fixes height, roll and pitch in a corridor) and
  // so do validation and fusion.
  const Cloud::Ptr featured = config.preprocess.remove_ground && m.cloud->size() > 100
                                  ? remove_ground(m.cloud, config.preprocess, units.tolerance)
                                  : m.cloud;
  m.coarse = voxel_grid(featured, config.describe.voxel_size * units.feature);
  // One tree over the coarse cloud serves its normals, ISS and the descriptors.
  const auto coarse_tree = std::make_shared<SerialKdTree<Point>>();
  coarse_tree->setInputCloud(m.coarse);
  estimate_normals(*m.coarse, *coarse_tree, config.describe.normal_radius * units.feature,
                   config.preprocess.orient_normals_to_free ? m.free_space.get() : nullptr, m.resolution);
  m.timings.preprocess_ms += ms_since(t0);

  t0 = Clock::now();
  const pcl::IndicesPtr indices = detect_iss(m.coarse, coarse_tree, config.keypoints, units.feature);
  m.timings.keypoints_ms += ms_since(t0);

  t0 = Clock::now();
  describe(m, coarse_tree, indices, config.describe, units.feature);
  m.timings.describe_ms += ms_since(t0);
}

/// Stages 1-2, and 4-5 when `features`, for a map of resolution `res` whose stage-1 points
/// `read_points` and free leaves `read_free` read.
template <class ReadPoints, class ReadFree>
PreparedMap prepare_stages(double res, ReadPoints&& read_points, ReadFree&& read_free, const AlignConfig& config,
                           bool features) {
  // PCL prints per-point warnings (degenerate ISS scatter, invalid SHOT frames) that the
  // pipeline already handles by dropping those points; results carry what matters.
  static std::once_flag quiet;
  std::call_once(quiet, [] { pcl::console::setVerbosityLevel(pcl::console::L_ERROR); });
  check_align_config(config);
  const auto t_start = Clock::now();
  auto m = std::make_shared<PreparedMap::Impl>();
  m->resolution = res;
  // The free space validation asks of this map, as sorted keys (~8 B a free leaf): the octree
  // itself (~57 B a node) is not kept.
  m->free_space = std::make_shared<const LeafSet>(read_free());

  auto t0 = Clock::now();
  const std::vector<OccupiedPoint> points = read_points();
  if (points.empty()) throw std::invalid_argument("map has no occupied voxel");
  m->num_points = points.size();
  m->timings.to_points_ms = ms_since(t0);

  t0 = Clock::now();
  m->full = to_cloud<FullPoint>(points);
  m->full_tree = std::make_shared<SerialKdTree<FullPoint>>();
  m->full_tree->setInputCloud(m->full);
  const LengthUnits units = length_units(m->resolution, config);
  m->cloud = preprocess(to_cloud<Point>(points), config.preprocess, units);
  if (m->cloud->size() < 10) throw std::invalid_argument("map has fewer than 10 points after preprocessing");
  // The ICP cloud's broad normals serve align()'s candidates; refine() and the last pass fit
  // fine ones on the cropped target themselves, so a map prepared for refine() has none.
  if (features) {
    SerialKdTree<Point> cloud_tree;  // only for these normals
    cloud_tree.setInputCloud(m->cloud);
    estimate_normals(*m->cloud, cloud_tree, config.preprocess.normal_radius * units.preprocess, nullptr,
                     m->resolution);
  }
  if (!features) {  // stages 1-2 only: what refine() and validate() read
    m->timings.preprocess_ms = ms_since(t0);
    m->timings.total_ms = ms_since(t_start);
    return PreparedMap(std::move(m));
  }
  m->timings.preprocess_ms = ms_since(t0);
  add_features(*m, config, units);
  m->timings.total_ms = ms_since(t_start);
  return PreparedMap(std::move(m));
}

PreparedMap prepare_tree(const octomap::OcTree& tree, const AlignConfig& config, bool features) {
  return prepare_stages(
      tree.getResolution(), [&] { return to_points(tree, config.points); },
      [&] { return LeafSet::of(tree, LeafState::kFree); }, config, features);
}

PreparedMap prepare_held(const HeldMap& map, const AlignConfig& config, bool features) {
  return prepare_stages(
      map.resolution(), [&] { return to_points(map, config.points); },
      [&] { return LeafSet::of(map, LeafState::kFree); }, config, features);
}

}  // namespace

std::shared_ptr<const PreparedMap::Impl> with_features(const PreparedMap::Impl& m, const AlignConfig& config) {
  check_align_config(config);
  const auto t0 = Clock::now();
  auto copy = std::make_shared<PreparedMap::Impl>(m);
  copy->timings = StageTimings{};
  copy->coarse.reset();
  copy->keypoints.reset();
  copy->fpfh.reset();
  copy->shot.reset();
  copy->fpfh_tree.reset();
  copy->shot_tree.reset();
  add_features(*copy, config, length_units(copy->resolution, config));
  copy->timings.total_ms = ms_since(t0);
  return copy;
}

PreparedMap prepare_map(const octomap::OcTree& tree, const AlignConfig& config) {
  return prepare_tree(tree, config, true);
}

PreparedMap prepare_for_refine(const octomap::OcTree& tree, const AlignConfig& config) {
  return prepare_tree(tree, config, false);
}

PreparedMap prepare_map(const HeldMap& map, const AlignConfig& config) { return prepare_held(map, config, true); }

PreparedMap prepare_for_refine(const HeldMap& map, const AlignConfig& config) {
  return prepare_held(map, config, false);
}

std::vector<std::size_t> ground_points(const std::vector<Eigen::Vector3f>& points,
                                       const PreprocessConfig& config, double unit) {
  const pcl::Indices ground = ground_indices(bare_cloud(points), config, unit);
  return std::vector<std::size_t>(ground.begin(), ground.end());
}

std::vector<std::size_t> iss_keypoints(const std::vector<Eigen::Vector3f>& points,
                                       const KeypointConfig& config, double unit) {
  const Cloud::Ptr cloud = bare_cloud(points);
  auto tree = std::make_shared<SerialKdTree<Point>>();
  tree->setInputCloud(cloud);
  const pcl::IndicesPtr indices = detect_iss(cloud, tree, config, unit);
  return std::vector<std::size_t>(indices->begin(), indices->end());
}

}  // namespace mapmerge::align
