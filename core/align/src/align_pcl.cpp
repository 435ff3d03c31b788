// Stages 3, 7, 8 and the orchestration of align / refine (PCL translation unit 3 of 3).
#include <atomic>
#include <chrono>
#include <mutex>
#include <sstream>

#include <Eigen/Cholesky>
#include <Eigen/Geometry>
// GCC 12 sees a 6x6 JacobiSVD inside PCL's NDT as "maybe uninitialized" (a false positive in
// system headers, reported since this unit inlines differently with FLANN's kd-tree in it).
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#include <pcl/registration/ndt.h>
#pragma GCC diagnostic pop
// NDT's voxel grids, instantiated here, not loaded from libpcl_filters (see prepare_pcl.cpp).
#include <pcl/filters/impl/voxel_grid.hpp>
#include <pcl/filters/impl/voxel_grid_covariance.hpp>
#include <tbb/global_control.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_invoke.h>
#include <tbb/parallel_reduce.h>
#include <tbb/task_arena.h>

#include "mapmerge/align/stages.hpp"
#include "prepared_map_impl.hpp"

namespace mapmerge::align {
namespace {

using Clock = std::chrono::steady_clock;
double ms_since(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

/// Adds elapsed milliseconds to a shared counter from several threads.
void add_ms(std::atomic<double>& total, Clock::time_point t0) {
  double cur = total.load();
  const double add = ms_since(t0);
  while (!total.compare_exchange_weak(cur, cur + add)) {
  }
}

double scale_of(const PreparedMap::Impl& a, const PreparedMap::Impl& b) {
  return std::max(a.resolution, b.resolution);
}

/// The "x res" unit of tolerances for a pair of maps [m] (LengthUnits::tolerance).
double tolerance_of(const PreparedMap::Impl& a, const PreparedMap::Impl& b, const AlignConfig& cfg) {
  return length_units(scale_of(a, b), cfg).tolerance;
}

// ---------------------------------------------------------------------------------------
// Stage 7: validation.

struct Counts {
  std::size_t inliers = 0, close = 0, conflicts = 0, near_conflicts = 0, checked = 0;
  double sum = 0.0;
};

/// The ranking's pair distance for the "x res" unit `res` [m]: validate.d_th, capped by
/// max_pair_distance but never below one voxel.
double close_distance(const ValidateConfig& c, double res) {
  const double d = c.d_th * res;
  return c.max_pair_distance > 0.0 ? std::max(std::min(d, c.max_pair_distance), res) : d;
}

/// Points of `from` (every `step`-th, full resolution) moved by T_to_from into `to`.
Counts check_direction(const PreparedMap::Impl& from, const PreparedMap::Impl& to,
                       const Eigen::Matrix4d& T_to_from, std::size_t samples,
                       const ValidateConfig& c, double res) {
  const Eigen::Matrix4f T = T_to_from.cast<float>();
  const std::size_t n = from.full->size();
  const std::size_t step = std::max<std::size_t>(1, n / std::max<std::size_t>(1, samples));
  const double d_th = c.d_th * res, d_close = close_distance(c, res), d_conflict = c.conflict_distance * res;
  // Nothing further than both distances changes the counts: the tree need not look beyond.
  const double reach = std::max(d_th, d_conflict);
  return tbb::parallel_reduce(
      tbb::blocked_range<std::size_t>(0, (n + step - 1) / step, 256), Counts{},
      [&](const tbb::blocked_range<std::size_t>& r, Counts acc) {
        pcl::Indices idx(1);
        std::vector<float> d2(1);
        for (std::size_t s = r.begin(); s < r.end(); ++s) {
          FullPoint p;
          p.getVector4fMap() = T * (*from.full)[s * step].getVector4fMap();
          ++acc.checked;
          const bool near = to.full_tree->radiusSearch(p, reach, idx, d2, 1) >= 1;
          const double d = near ? std::sqrt(static_cast<double>(d2[0])) : std::numeric_limits<double>::infinity();
          const auto seen_free = [&] { return to.free_space->contains(Eigen::Vector3d(p.x, p.y, p.z)); };
          if (d <= d_th) {
            ++acc.inliers;
            acc.sum += d;
            if (d <= d_close) {
              ++acc.close;
            } else if (seen_free()) {
              ++acc.near_conflicts;
            }
          } else if (d > d_conflict && seen_free()) {
            ++acc.conflicts;
          }
        }
        return acc;
      },
      [](Counts a, const Counts& b) {
        a.inliers += b.inliers;
        a.close += b.close;
        a.conflicts += b.conflicts;
        a.near_conflicts += b.near_conflicts;
        a.checked += b.checked;
        a.sum += b.sum;
        return a;
      });
}

/// Angle between the target's z axis and the source's under T_target_source [deg]: (R e_z) . e_z.
double tilt_deg(const Eigen::Matrix4d& T_target_source) {
  return std::acos(std::clamp(T_target_source(2, 2), -1.0, 1.0)) * 180.0 / M_PI;
}

/// Both directions: source into target and target into source; `res`: the "x res" unit.
Validation check(const PreparedMap::Impl& target, const PreparedMap::Impl& source,
                 const Eigen::Matrix4d& T_target_source, std::size_t samples,
                 const ValidateConfig& c, std::size_t n_th, double res) {
  const Counts a = check_direction(source, target, T_target_source, samples, c, res);
  const Counts b = check_direction(target, source, T_target_source.inverse(), samples, c, res);
  Validation v;
  v.inliers = a.inliers + b.inliers;
  v.close_pairs = a.close + b.close;
  v.conflicts = a.conflicts + b.conflicts;
  v.near_conflicts = a.near_conflicts + b.near_conflicts;
  v.checked = a.checked + b.checked;
  const bool enough = v.inliers >= n_th && v.inliers > 0;
  v.fitness = enough ? (a.sum + b.sum) / static_cast<double>(v.inliers)
                     : std::numeric_limits<double>::infinity();
  const double seen = static_cast<double>(v.inliers + v.conflicts);
  v.overlap = v.checked ? seen / static_cast<double>(v.checked) : 0.0;
  v.inlier_share = seen > 0.0 ? static_cast<double>(v.inliers) / seen : 0.0;
  v.inlier_fraction = v.checked ? static_cast<double>(v.inliers) / static_cast<double>(v.checked) : 0.0;
  v.near_conflict_share = v.inliers ? static_cast<double>(v.near_conflicts) / static_cast<double>(v.inliers) : 0.0;
  v.tilt_deg = tilt_deg(T_target_source);
  return v;
}

/// Ranking score of a validated transform: close agreement minus weighted contradiction (far
/// and near conflicts alike).
double score_of(const Validation& v, double conflict_weight) {
  return static_cast<double>(v.close_pairs) - conflict_weight * static_cast<double>(v.conflicts + v.near_conflicts);
}

/// Empty string when `v` passes every acceptance test, else the reason.
std::string rejection(const Validation& v, const ValidateConfig& c, double res) {
  std::ostringstream why;
  if (v.tilt_deg > c.max_tilt_deg) {
    why << "tilts the source's z axis " << v.tilt_deg << " deg from the target's, above validate.max_tilt_deg "
        << c.max_tilt_deg;
  } else if (!std::isfinite(v.fitness)) {
    why << "fewer than n_th=" << c.n_th << " point pairs within d_th (" << v.inliers << ")";
  } else if (v.fitness > c.max_fitness * res) {
    why << "fitness " << v.fitness << " m above " << c.max_fitness * res << " m";
  } else if (v.inlier_fraction < c.min_inlier_fraction) {
    why << "inlier fraction " << v.inlier_fraction << " below " << c.min_inlier_fraction;
  } else if (v.inlier_share < c.min_inlier_share) {
    why << "contradicts free space: inlier share " << v.inlier_share << " below "
        << c.min_inlier_share;
  } else if (v.near_conflict_share > c.max_near_conflict_share) {
    why << "near conflicts: " << v.near_conflict_share << " of the pairs within d_th lie in the other map's free space "
        << "beyond " << close_distance(c, res) << " m of its surfaces, above validate.max_near_conflict_share "
        << c.max_near_conflict_share;
  }
  return why.str();
}

// ---------------------------------------------------------------------------------------
// Stage 8: local alignment.

/// Points of `target` (a target cloud) inside the source's box (moved into the target frame)
/// inflated by d_m.
Cloud::Ptr crop_target(const Cloud& target, const PreparedMap::Impl& source, const Eigen::Matrix4d& T,
                       double margin) {
  Eigen::Vector3f lo = Eigen::Vector3f::Constant(std::numeric_limits<float>::max());
  Eigen::Vector3f hi = -lo;
  const Eigen::Matrix4f Tf = T.cast<float>();
  for (const auto& p : *source.cloud) {
    const Eigen::Vector3f q = (Tf * p.getVector4fMap()).head<3>();
    lo = lo.cwiseMin(q);
    hi = hi.cwiseMax(q);
  }
  const Eigen::Vector3f m = Eigen::Vector3f::Constant(static_cast<float>(margin));
  lo -= m;
  hi += m;
  auto crop = std::make_shared<Cloud>();
  for (const auto& p : target) {
    const Eigen::Vector3f q = p.getVector3fMap();
    if ((q.array() >= lo.array()).all() && (q.array() <= hi.array()).all()) crop->push_back(p);
  }
  return crop;
}

struct Normal6 {
  Eigen::Matrix<double, 6, 6> A = Eigen::Matrix<double, 6, 6>::Zero();
  Eigen::Matrix<double, 6, 1> b = Eigen::Matrix<double, 6, 1>::Zero();
  std::size_t pairs = 0;
};

/// One Gauss-Newton step of (occupancy-weighted) point-to-plane or point-to-point ICP. Pairs
/// are nearest neighbours within `nn_max`; point-to-plane gates on the plane distance `dmax`
/// (a target point stands for a voxel-grid cell, so the in-plane offset is not an error).
Normal6 icp_system(const Cloud& src, std::size_t step, const Cloud& tgt,
                   const SerialKdTree<Point>& tree, const Eigen::Matrix4d& T, double dmax,
                   double nn_max, const RefineConfig& c, double sigma) {
  const Eigen::Matrix4f Tf = T.cast<float>();
  const bool weighted = c.method == RefineMethod::kOicp;
  const auto nn_max2 = static_cast<float>(std::max(nn_max, dmax) * std::max(nn_max, dmax));
  const auto dmax2 = static_cast<float>(dmax * dmax);
  auto body = [&](const tbb::blocked_range<std::size_t>& r, Normal6 acc) {
    pcl::Indices idx(1);
    std::vector<float> d2(1);
    for (std::size_t s = r.begin(); s < r.end(); ++s) {
      const Point& sp = src[s * step];
      Point p;
      p.getVector4fMap() = Tf * sp.getVector4fMap();
      if (tree.nearestKSearch(p, 1, idx, d2) < 1) continue;
      if (d2[0] > (c.point_to_plane ? nn_max2 : dmax2)) continue;
      const Point& q = tgt[idx[0]];
      const Eigen::Vector3d pd = p.getVector3fMap().cast<double>();
      const Eigen::Vector3d diff = pd - q.getVector3fMap().cast<double>();
      double w = weighted ? static_cast<double>(sp.intensity) * q.intensity : 1.0;
      if (c.point_to_plane) {
        const Eigen::Vector3d n = q.getNormalVector3fMap().cast<double>();
        if (!n.allFinite()) continue;  // no plane at this target point
        const double r0 = diff.dot(n);
        if (r0 * r0 > dmax * dmax) continue;
        w /= 1.0 + (r0 * r0) / (sigma * sigma);  // Cauchy-like robust weight
        Eigen::Matrix<double, 6, 1> J;
        J << pd.cross(n), n;
        acc.A += w * J * J.transpose();
        acc.b += w * J * r0;
      } else {
        w /= 1.0 + diff.squaredNorm() / (sigma * sigma);
        Eigen::Matrix<double, 3, 6> J;
        J.setZero();
        J.rightCols<3>().setIdentity();
        J(0, 1) = pd.z(); J(0, 2) = -pd.y();
        J(1, 0) = -pd.z(); J(1, 2) = pd.x();
        J(2, 0) = pd.y(); J(2, 1) = -pd.x();
        acc.A += w * J.transpose() * J;
        acc.b += w * J.transpose() * diff;
      }
      ++acc.pairs;
    }
    return acc;
  };
  const std::size_t count = (src.size() + step - 1) / step;
  return tbb::parallel_reduce(tbb::blocked_range<std::size_t>(0, count, 512), Normal6{}, body,
                              [](Normal6 a, const Normal6& b) {
                                a.A += b.A;
                                a.b += b.b;
                                a.pairs += b.pairs;
                                return a;
                              });
}

/// Full-resolution source points that have a target point within `dmax` under T0: ICP spends
/// its budget on the overlap only (at 10 % overlap most of a map has no partner).
Cloud overlap_sample(const FullCloud& full, const SerialKdTree<Point>& tree, const Eigen::Matrix4d& T0,
                     double dmax, std::size_t max_points) {
  const std::size_t probe_step = std::max<std::size_t>(1, full.size() / (2 * max_points));
  const Eigen::Matrix4f T = T0.cast<float>();
  const auto dmax2 = static_cast<float>(dmax * dmax);
  Cloud kept;
  pcl::Indices idx(1);
  std::vector<float> d2(1);
  for (std::size_t i = 0; i < full.size(); i += probe_step) {
    Point p;
    p.getVector4fMap() = T * full[i].getVector4fMap();
    if (tree.radiusSearch(p, dmax, idx, d2, 1) == 1 && d2[0] <= dmax2) {
      // Without a normal: ICP reads the target's planes only.
      kept.push_back(Point(full[i].x, full[i].y, full[i].z, full[i].intensity));
    }
  }
  if (kept.size() <= max_points) return kept;
  Cloud out;
  const double stride = static_cast<double>(kept.size()) / static_cast<double>(max_points);
  for (std::size_t i = 0; i < max_points; ++i) out.push_back(kept[static_cast<std::size_t>(i * stride)]);
  return out;
}

/// ICP of the source's full-resolution points onto `target_crop` (its kd-tree `tree`). With
/// `ramp`, the pair distance shrinks from max_correspondence to final_correspondence over the
/// first third of the iterations; without, it is final_correspondence throughout (a start that
/// is already refined).
Eigen::Matrix4d icp(const PreparedMap::Impl& source, const Cloud::Ptr& target_crop,
                    const SerialKdTree<Point>& tree, const Eigen::Matrix4d& T0, const RefineConfig& c,
                    const LengthUnits& units, std::size_t max_points, int iterations, bool ramp) {
  // Source: full-resolution voxel centres (not the downsampled cloud), so the result is not
  // quantised by the describe voxel; target: downsampled points with their local planes.
  const double last = c.final_correspondence * units.tolerance;
  const double first = ramp ? std::max(c.max_correspondence * units.feature, 2.0 * last) : last;
  const Cloud src = overlap_sample(*source.full, tree, T0, first, max_points);
  Eigen::Matrix4d T = T0;
  const int ramp_its = std::max(1, iterations / 3);  // iterations to reach final_correspondence
  for (int it = 0; it < iterations; ++it) {
    const double f = ramp ? std::min(1.0, static_cast<double>(it) / ramp_its) : 1.0;
    const double dmax = first + f * (last - first);
    const Normal6 sys = icp_system(src, 1, *target_crop, tree, T, dmax, first, c, dmax / 2.0);
    if (sys.pairs < 6) break;
    const Eigen::Matrix<double, 6, 6> A = sys.A + 1e-6 * sys.A.trace() * Eigen::Matrix<double, 6, 6>::Identity();
    const Eigen::Matrix<double, 6, 1> x = -A.ldlt().solve(sys.b);
    if (!x.allFinite()) break;
    Eigen::Matrix4d dT = Eigen::Matrix4d::Identity();
    const double angle = x.head<3>().norm();
    if (angle > 0.0) dT.topLeftCorner<3, 3>() = Eigen::AngleAxisd(angle, x.head<3>() / angle).toRotationMatrix();
    dT.topRightCorner<3, 1>() = x.tail<3>();
    T = dT * T;
    if (x.tail<3>().norm() < c.convergence_translation * units.tolerance &&
        angle * 180.0 / M_PI < c.convergence_rotation_deg && f >= 1.0)
      break;
  }
  return T;
}

Eigen::Matrix4d ndt(const PreparedMap::Impl& source, const Cloud::Ptr& target_crop,
                    const Eigen::Matrix4d& T0, const RefineConfig& c, const LengthUnits& units) {
  if (target_crop->size() < 10) return T0;
  auto src = std::make_shared<Cloud>();
  const std::size_t step = std::max<std::size_t>(1, source.cloud->size() / c.max_points);
  for (std::size_t i = 0; i < source.cloud->size(); i += step) src->push_back((*source.cloud)[i]);
  pcl::NormalDistributionsTransform<Point, Point> reg;
  reg.setResolution(static_cast<float>(c.ndt_resolution * units.refine));
  reg.setStepSize(c.ndt_step * units.refine);
  reg.setTransformationEpsilon(c.convergence_translation * units.tolerance);
  reg.setMaximumIterations(c.max_iterations);
  reg.setInputTarget(target_crop);
  reg.setInputSource(src);
  Cloud out;
  reg.align(out, T0.cast<float>());
  if (!reg.hasConverged()) return T0;
  return reg.getFinalTransformation().cast<double>();
}

/// Stage 8's passes: a candidate's first refinement; the final pass on the chosen transform
/// (final_points); that pass on fine normals (preprocess.fine_normal_radius), once the verdict
/// is taken and in refine(). `from_polished`: the start is a polished transform, so no
/// pair-distance ramp.
enum class Pass { kCandidate, kPolish, kFine };

Eigen::Matrix4d local_alignment(const PreparedMap::Impl& target, const PreparedMap::Impl& source,
                                const Eigen::Matrix4d& T0, const AlignConfig& cfg, Pass pass,
                                bool from_polished = false) {
  const RefineConfig& c = cfg.refine;
  if (c.method == RefineMethod::kNone) return T0;
  const LengthUnits units = length_units(scale_of(target, source), cfg);
  const Cloud::Ptr crop = crop_target(*target.cloud, source, T0, c.crop_margin * units.refine);
  if (c.method == RefineMethod::kNdt) return pass == Pass::kCandidate ? ndt(source, crop, T0, c, units) : T0;
  if (crop->size() < 10) return T0;
  SerialKdTree<Point> tree;
  tree.setInputCloud(crop);
  if (pass == Pass::kFine) {
    // Fine planes, fitted on the crop only (the d_m margin keeps its cut far from the overlap).
    estimate_normals(*crop, tree, cfg.preprocess.fine_normal_radius * units.preprocess, nullptr, units.res);
  }
  const bool candidate = pass == Pass::kCandidate;
  return icp(source, crop, tree, T0, c, units, candidate ? c.max_points : c.final_points,
             candidate ? c.max_iterations : c.final_iterations, !from_polished);
}

// ---------------------------------------------------------------------------------------
// Orchestration.

struct Candidate {
  Hypothesis h;
  Validation coarse;
  Eigen::Matrix4d T_refined = Eigen::Matrix4d::Identity();
  Validation fine;
};

void add_prepare_timings(StageTimings& t, const StageTimings& m) {
  t.to_points_ms += m.to_points_ms;
  t.preprocess_ms += m.preprocess_ms;
  t.keypoints_ms += m.keypoints_ms;
  t.describe_ms += m.describe_ms;
}

/// Source keypoint subsets: the blocks of stage 3 in spiral order, or the whole map.
std::vector<std::vector<int>> keypoint_subsets(const PreparedMap::Impl& source,
                                               const SubmodelConfig& c, double unit) {
  std::vector<std::vector<int>> subsets;
  const std::size_t n = source.keypoints->size();
  if (!c.enabled) {
    subsets.emplace_back(n);
    for (std::size_t i = 0; i < n; ++i) subsets.back()[i] = static_cast<int>(i);
    return subsets;
  }
  std::vector<Eigen::Vector3f> positions;
  positions.reserve(n);
  for (const auto& p : *source.keypoints) positions.push_back(p.getVector3fMap());
  for (const Block& b : make_submodels(positions, c, unit)) {
    if (b.members.size() < c.min_keypoints) continue;
    subsets.emplace_back(b.members.begin(), b.members.end());
  }
  return subsets;
}

/// Stage 3 + 6 + coarse 7: hypotheses of every block (spiral order, on the thread pool).
std::vector<Candidate> search_blocks(const PreparedMap::Impl& target, const PreparedMap::Impl& source,
                                     const std::vector<Match>& matches,
                                     const std::vector<std::vector<int>>& subsets,
                                     const AlignConfig& cfg, std::atomic<double>& match_ms,
                                     std::atomic<double>& validate_ms, std::size_t& raw, const Cancel& cancel) {
  const double res = tolerance_of(target, source, cfg);
  std::vector<Candidate> found;
  std::mutex lock;
  std::atomic<std::size_t> next{0}, raw_count{0};
  std::atomic<bool> stop{false};
  const ValidateConfig& vc = cfg.validate;
  auto worker = [&](int) {
    for (std::size_t i = next++; i < subsets.size() && !stop && !(cancel && cancel()); i = next++) {
      auto t0 = Clock::now();
      std::vector<Hypothesis> hyps = generate_hypotheses(target, source, matches, subsets[i], cfg,
                                                         cfg.seed + static_cast<unsigned>(i));
      add_ms(match_ms, t0);
      raw_count += hyps.size();
      t0 = Clock::now();
      for (Hypothesis& h : hyps) {
        // One tilted beyond the bound cannot pass: it is not checked, cannot stop the search
        // early, and takes no refinement slot from an upright one.
        if (tilt_deg(h.T_target_source) > vc.max_tilt_deg) continue;
        h.submodel = cfg.submodels.enabled ? static_cast<int>(i) : -1;
        Candidate cand;
        cand.h = h;
        cand.coarse = check(target, source, h.T_target_source, vc.coarse_points, vc, 1, res);
        const bool good = cand.coarse.inlier_share >= cfg.submodels.early_stop_inlier_share &&
                          cand.coarse.inlier_fraction >= vc.min_inlier_fraction &&
                          cand.coarse.fitness <= vc.max_fitness * res;
        std::lock_guard<std::mutex> g(lock);
        found.push_back(cand);
        if (good && cfg.submodels.enabled && cfg.submodels.early_stop) stop = true;
      }
      add_ms(validate_ms, t0);
    }
  };
  const int threads = cfg.submodels.threads > 0 ? cfg.submodels.threads
                                                : tbb::this_task_arena::max_concurrency();
  const int workers = static_cast<int>(std::min<std::size_t>(subsets.size(), static_cast<std::size_t>(threads)));
  tbb::parallel_for(0, std::max(1, workers), worker);
  raw = raw_count;
  return found;
}

/// Keeps the best distinct candidates by coarse score.
std::vector<Candidate> shortlist(std::vector<Candidate> all, const ValidateConfig& c,
                                 const LengthUnits& units) {
  const double w = c.conflict_weight;
  std::sort(all.begin(), all.end(), [w](const Candidate& a, const Candidate& b) {
    return score_of(a.coarse, w) > score_of(b.coarse, w);
  });
  std::vector<Candidate> out;
  const double floor = all.empty() ? 0.0 : c.refine_score_ratio * score_of(all.front().coarse, c.conflict_weight);
  for (const Candidate& cand : all) {
    if (score_of(cand.coarse, c.conflict_weight) < floor || score_of(cand.coarse, c.conflict_weight) <= 0.0) break;
    // Raw hypotheses are a few voxels off, so they may contradict a little; far off, they cannot win.
    if (cand.coarse.inlier_share < c.min_inlier_share - 0.25 ||
        cand.coarse.inlier_fraction < c.min_inlier_fraction / 2.0)
      continue;
    bool dup = false;
    for (const Candidate& o : out)
      dup = dup || same_pose(o.h.T_target_source, cand.h.T_target_source, c.distinct_rotation_deg,
                             c.distinct_translation * units.feature);
    if (!dup) out.push_back(cand);
    if (out.size() >= c.refine_candidates) break;
  }
  return out;
}

std::size_t fine_samples(const ValidateConfig& c) { return c.coarse_points * 2; }

constexpr const char* kAmbiguous = "ambiguous";
constexpr const char* kCancelled = "cancelled";
constexpr const char* kNoFeatures = "a map was prepared without features (prepare_for_refine)";

/// Sorts refined candidates by score and brings the best one that passes every test to the
/// front. Empty string when there is one and no distinct alternative comes close (repetitive
/// corridors, symmetric rooms), else the reason: the top candidate's refusal when none passes.
/// An alternative that free space contradicts (inlier share below min_inlier_share) is no rival
/// and does not outrank: a corridor slid along itself overlaps more and so agrees at more points
/// than the truth (fr_079 <- geb079 at 10 %: 3850 inliers against 1160), but ~9 % of its points
/// land in the other map's free space, which the truth's do not.
std::string select_best(std::vector<Candidate>& cands, const ValidateConfig& c,
                        const LengthUnits& units) {
  const double res = units.tolerance;
  const double w = c.conflict_weight;
  std::sort(cands.begin(), cands.end(), [w](const Candidate& a, const Candidate& b) {
    return score_of(a.fine, w) > score_of(b.fine, w);
  });
  const auto passing = std::find_if(cands.begin(), cands.end(),
                                    [&](const Candidate& k) { return rejection(k.fine, c, res).empty(); });
  if (passing == cands.end()) return rejection(cands.front().fine, c, res);
  std::rotate(cands.begin(), passing, passing + 1);
  const Candidate& best = cands.front();
  for (std::size_t i = 1; i < cands.size(); ++i) {
    if (cands[i].fine.inlier_share < c.min_inlier_share ||
        same_pose(best.T_refined, cands[i].T_refined, c.distinct_rotation_deg, c.distinct_translation * units.feature))
      continue;
    const double ratio = score_of(cands[i].fine, w) / std::max(1.0, score_of(best.fine, w));
    if (ratio >= c.ambiguity_ratio)
      return kAmbiguous + std::string(": a distinct transform scores ") + std::to_string(ratio) + " of the best";
  }
  return {};
}

/// A final ICP pass (`pass`) on a candidate; kept when it passes validation and scores at
/// least `keep_ratio` of what the candidate scored before.
void polish(const PreparedMap::Impl& target, const PreparedMap::Impl& source,
            const AlignConfig& cfg, Candidate& best, StageTimings& t,
            std::atomic<double>& validate_ms, double keep_ratio, Pass pass = Pass::kPolish,
            bool from_polished = false) {
  const double res = tolerance_of(target, source, cfg);
  auto t0 = Clock::now();
  const Eigen::Matrix4d T = local_alignment(target, source, best.T_refined, cfg, pass, from_polished);
  t.refine_ms += ms_since(t0);
  t0 = Clock::now();
  const Validation v = check(target, source, T, fine_samples(cfg.validate), cfg.validate, cfg.validate.n_th, res);
  add_ms(validate_ms, t0);
  const double w = cfg.validate.conflict_weight;
  if (rejection(v, cfg.validate, res).empty() && score_of(v, w) >= keep_ratio * score_of(best.fine, w)) {
    best.T_refined = T;
    best.fine = v;
  }
}

/// The final pass can stop in a local minimum a few degrees off when the overlap is narrow (a
/// strip constrains a turn about its own length weakly; fr_078_tidyup at 10 %: 3.2 deg and 0.5 m
/// off, fitness 0.034 where the truth fits at 0.027). When the fit is that loose
/// (refine.restart_fitness), ICP starts again from the result turned by +-refine.restart_deg
/// about each axis through the middle of the target's crop; the restart with the closest fit
/// that passes validation and keeps the score (keep_ratio) replaces it.
void restart_from_turns(const PreparedMap::Impl& target, const PreparedMap::Impl& source,
                        const AlignConfig& cfg, Candidate& best, StageTimings& t,
                        std::atomic<double>& validate_ms, double keep_ratio) {
  const double deg = cfg.refine.restart_deg;
  const double map_res = scale_of(target, source);
  if (deg <= 0.0 || !(best.fine.fitness > cfg.refine.restart_fitness * map_res)) return;
  const LengthUnits units = length_units(map_res, cfg);
  const double res = units.tolerance;
  const double w = cfg.validate.conflict_weight;
  const Cloud::Ptr crop = crop_target(*target.cloud, source, best.T_refined, cfg.refine.crop_margin * units.refine);
  if (crop->size() < 10) return;
  Eigen::Vector3d centre = Eigen::Vector3d::Zero();
  for (const auto& p : *crop) centre += p.getVector3fMap().cast<double>();
  centre /= static_cast<double>(crop->size());
  const Candidate start = best;
  for (int axis = 0; axis < 3; ++axis) {
    for (const double sign : {-1.0, 1.0}) {
      const Eigen::Affine3d turn = Eigen::Translation3d(centre) *
                             Eigen::AngleAxisd(sign * deg * M_PI / 180.0, Eigen::Vector3d::Unit(axis)) *
                             Eigen::Translation3d(-centre);
      auto t0 = Clock::now();
      const Eigen::Matrix4d T = local_alignment(target, source, turn.matrix() * start.T_refined, cfg, Pass::kFine);
      t.refine_ms += ms_since(t0);
      t0 = Clock::now();
      const Validation v = check(target, source, T, fine_samples(cfg.validate), cfg.validate, cfg.validate.n_th, res);
      add_ms(validate_ms, t0);
      if (rejection(v, cfg.validate, res).empty() && v.fitness < best.fine.fitness &&
          score_of(v, w) >= keep_ratio * score_of(start.fine, w)) {
        best.T_refined = T;
        best.fine = v;
      }
    }
  }
}

/// The chosen candidate's last refinement, once the verdict is taken: the final pass on fine
/// planes (sub-voxel, none averaged across a coarse map's staircase), then restarts when its fit
/// is loose. `from_polished`: the start is a polished transform (no pair-distance ramp).
void final_pass(const PreparedMap::Impl& target, const PreparedMap::Impl& source, const AlignConfig& cfg,
                Candidate& best, StageTimings& t, std::atomic<double>& validate_ms, bool from_polished) {
  polish(target, source, cfg, best, t, validate_ms, 0.98, Pass::kFine, from_polished);
  restart_from_turns(target, source, cfg, best, t, validate_ms, 0.98);
}

/// One global search (stages 3, 6-8) on the maps' features as prepared.
AlignResult search(const PreparedMap::Impl& target, const PreparedMap::Impl& source, const AlignConfig& cfg,
                   const Cancel& cancel) {
  const auto t_all = Clock::now();
  const double res = scale_of(target, source);
  AlignResult result;
  add_prepare_timings(result.timings, target.timings);
  add_prepare_timings(result.timings, source.timings);
  std::atomic<double> match_ms{0.0}, validate_ms{0.0};
  auto finish = [&](std::string reason) {
    result.reason = std::move(reason);
    result.timings.match_ms = match_ms;
    result.timings.validate_ms = validate_ms;
    result.timings.total_ms = ms_since(t_all);
    return result;
  };
  const auto cancelled = [&] { return cancel && cancel(); };
  if (!source.keypoints || !target.keypoints) return finish(kNoFeatures);
  if (source.keypoints->size() < 3 || target.keypoints->size() < 3)
    return finish("too few keypoints (target " + std::to_string(target.keypoints->size()) +
                  ", source " + std::to_string(source.keypoints->size()) + ")");
  auto t0 = Clock::now();
  const std::vector<Match> matches = match_descriptors(target, source, cfg.match);
  add_ms(match_ms, t0);
  t0 = Clock::now();
  const LengthUnits units = length_units(res, cfg);
  const auto subsets = keypoint_subsets(source, cfg.submodels, units.feature);
  result.timings.submodels_ms = ms_since(t0);
  std::vector<Candidate> cands =
      shortlist(search_blocks(target, source, matches, subsets, cfg, match_ms, validate_ms,
                              result.hypotheses, cancel),
                cfg.validate, units);
  if (cancelled()) return finish(kCancelled);
  if (cands.empty())
    return finish("no hypothesis agrees with the maps (" + std::to_string(result.hypotheses) +
                  " raw, from " + std::to_string(matches.size()) + " correspondences)");
  t0 = Clock::now();
  for (Candidate& c : cands) {
    if (cancelled()) return finish(kCancelled);
    c.T_refined = local_alignment(target, source, c.h.T_target_source, cfg, Pass::kCandidate);
  }
  result.timings.refine_ms = ms_since(t0);
  t0 = Clock::now();
  for (Candidate& c : cands)
    c.fine = check(target, source, c.T_refined, fine_samples(cfg.validate), cfg.validate, cfg.validate.n_th,
                   units.tolerance);
  std::string why = select_best(cands, cfg.validate, units);
  add_ms(validate_ms, t0);
  if (cancelled()) return finish(kCancelled);
  if (why.empty()) {
    // With the pair-distance ramp: a candidate may still be degrees off.
    final_pass(target, source, cfg, cands.front(), result.timings, validate_ms, false);
  } else if (ambiguous_refusal(why)) {
    // Near-equal distinct candidates are often one basin that the first ICP left apart: the
    // final pass brings them together (then one is a duplicate) or shows which one is better.
    // A pass is kept only if it scores no lower, so no alternative can fall below the ambiguity
    // ratio by being polished worse.
    for (Candidate& c : cands) polish(target, source, cfg, c, result.timings, validate_ms, 1.0);
    t0 = Clock::now();
    why = select_best(cands, cfg.validate, units);
    add_ms(validate_ms, t0);
    if (why.empty())  // polished already: fine planes from there, at the last pair distance
      final_pass(target, source, cfg, cands.front(), result.timings, validate_ms, true);
  }
  Candidate& best = cands.front();
  result.accepted = why.empty();
  result.T_target_source = result.accepted ? best.T_refined : Eigen::Matrix4d::Identity();
  result.fitness = best.fine.fitness;
  result.inliers = best.fine.inliers;
  result.overlap = best.fine.overlap;
  result.inlier_share = best.fine.inlier_share;
  result.submodel = best.h.submodel;
  return finish(why);
}

void add_timings(StageTimings& t, const StageTimings& more) {
  add_prepare_timings(t, more);
  t.submodels_ms += more.submodels_ms;
  t.match_ms += more.match_ms;
  t.validate_ms += more.validate_ms;
  t.refine_ms += more.refine_ms;
}

}  // namespace

namespace {

/// The rescue's search (AlignConfig::rescue): the same maps' stages 1-2, denser features.
AlignResult dense_search(const PreparedMap::Impl& target, const PreparedMap::Impl& source, const AlignConfig& cfg,
                         const Cancel& cancel) {
  AlignConfig dense = cfg;
  dense.describe.voxel_size = cfg.rescue.describe_voxel_size;
  dense.keypoints.non_max_radius = cfg.rescue.non_max_radius;
  dense.rescue.enabled = false;
  std::shared_ptr<const PreparedMap::Impl> dense_target, dense_source;
  AlignResult r;
  r.rescued = true;
  r.reason = kCancelled;
  if (cancel && cancel()) return r;
  tbb::parallel_invoke([&] { dense_target = with_features(target, dense); },
                       [&] { dense_source = with_features(source, dense); });
  if (cancel && cancel()) return r;
  r = search(*dense_target, *dense_source, dense, cancel);
  r.rescued = true;
  return r;
}

bool has_keypoints(const PreparedMap::Impl& m) { return m.keypoints != nullptr; }

}  // namespace

bool ambiguous_refusal(const std::string& reason) { return reason.rfind(kAmbiguous, 0) == 0; }

AlignResult align(const PreparedMap& target_map, const PreparedMap& source_map, const AlignConfig& cfg,
                  const Cancel& cancel) {
  const auto t_all = Clock::now();
  const PreparedMap::Impl& target = target_map.impl();
  const PreparedMap::Impl& source = source_map.impl();
  AlignResult first = search(target, source, cfg, cancel);
  // The rescue (AlignConfig::rescue): a second search on denser features, when the first found
  // nothing that fits (not when two distinct transforms fit: a symmetry stays refused).
  if (first.accepted || !cfg.rescue.enabled || !has_keypoints(target) || !has_keypoints(source) ||
      ambiguous_refusal(first.reason) || first.reason == kCancelled)
    return first;
  AlignResult second = dense_search(target, source, cfg, cancel);
  second.hypotheses += first.hypotheses;
  StageTimings t = first.timings;
  add_timings(t, second.timings);
  second.timings = t;
  second.timings.total_ms = ms_since(t_all);
  if (!second.accepted) second.reason = first.reason + "; on denser features: " + second.reason;
  return second;
}

AlignResult rescue(const PreparedMap& target_map, const PreparedMap& source_map, const AlignConfig& cfg,
                   const Cancel& cancel) {
  const auto t_all = Clock::now();
  const PreparedMap::Impl& target = target_map.impl();
  const PreparedMap::Impl& source = source_map.impl();
  if (!has_keypoints(target) || !has_keypoints(source)) {
    AlignResult r;
    r.reason = kNoFeatures;
    return r;
  }
  AlignResult r = dense_search(target, source, cfg, cancel);
  r.timings.total_ms = ms_since(t_all);
  return r;
}

AlignResult refine(const PreparedMap& target_map, const PreparedMap& source_map,
                   const Eigen::Matrix4d& T_target_source_init, const AlignConfig& cfg) {
  const auto t_all = Clock::now();
  const PreparedMap::Impl& target = target_map.impl();
  const PreparedMap::Impl& source = source_map.impl();
  AlignResult result;
  auto t0 = Clock::now();
  const Eigen::Matrix4d T = local_alignment(target, source, T_target_source_init, cfg, Pass::kFine);
  result.timings.refine_ms = ms_since(t0);
  t0 = Clock::now();
  const double tol = tolerance_of(target, source, cfg);
  const Validation v = check(target, source, T, fine_samples(cfg.validate), cfg.validate, cfg.validate.n_th, tol);
  result.timings.validate_ms = ms_since(t0);
  result.reason = rejection(v, cfg.validate, tol);
  result.accepted = result.reason.empty();
  result.T_target_source = result.accepted ? T : T_target_source_init;
  result.fitness = v.fitness;
  result.inliers = v.inliers;
  result.overlap = v.overlap;
  result.inlier_share = v.inlier_share;
  result.timings.total_ms = ms_since(t_all);
  return result;
}

Validation validate(const PreparedMap& target, const PreparedMap& source,
                    const Eigen::Matrix4d& T_target_source, const AlignConfig& cfg) {
  return check(target.impl(), source.impl(), T_target_source, fine_samples(cfg.validate),
               cfg.validate, cfg.validate.n_th, tolerance_of(target.impl(), source.impl(), cfg));
}

namespace {

template <class Map>
AlignResult prepare_and_align(const Map& target, const Map& source, const AlignConfig& config) {
  const auto t_all = Clock::now();
  PreparedMap t, s;
  tbb::parallel_invoke([&] { t = prepare_map(target, config); }, [&] { s = prepare_map(source, config); });
  AlignResult r = align(t, s, config);
  r.timings.total_ms = ms_since(t_all);
  return r;
}

}  // namespace

AlignResult align_maps(const octomap::OcTree& target, const octomap::OcTree& source, const AlignConfig& config) {
  return prepare_and_align(target, source, config);
}

AlignResult align_maps(const HeldMap& target, const HeldMap& source, const AlignConfig& config) {
  return prepare_and_align(target, source, config);
}

Fitness fitness_score(const std::vector<Eigen::Vector3f>& source_in_target,
                      const std::vector<Eigen::Vector3f>& target, double d_th, std::size_t n_th) {
  if (target.empty()) return fitness_from_distances({}, d_th, n_th);
  auto cloud = std::make_shared<Cloud>();
  for (const auto& p : target) {
    Point q;
    q.getVector3fMap() = p;
    cloud->push_back(q);
  }
  SerialKdTree<Point> tree;
  tree.setInputCloud(cloud);
  std::vector<double> distances;
  pcl::Indices idx(1);
  std::vector<float> d2(1);
  for (const auto& p : source_in_target) {
    Point q;
    q.getVector3fMap() = p;
    if (tree.nearestKSearch(q, 1, idx, d2) == 1) distances.push_back(std::sqrt(static_cast<double>(d2[0])));
  }
  return fitness_from_distances(distances, d_th, n_th);
}

std::string timings_json(const StageTimings& t) {
  std::ostringstream o;
  o << "{\"to_points_ms\":" << t.to_points_ms << ",\"preprocess_ms\":" << t.preprocess_ms
    << ",\"keypoints_ms\":" << t.keypoints_ms << ",\"describe_ms\":" << t.describe_ms
    << ",\"submodels_ms\":" << t.submodels_ms << ",\"match_ms\":" << t.match_ms
    << ",\"validate_ms\":" << t.validate_ms << ",\"refine_ms\":" << t.refine_ms
    << ",\"total_ms\":" << t.total_ms << "}";
  return o.str();
}

}  // namespace mapmerge::align
