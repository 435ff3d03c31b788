// Stage 6: descriptor correspondences and global hypotheses (PCL translation unit 2 of 3).
#include <algorithm>
#include <array>
#include <cstdint>
#include <random>
#include <unordered_set>

#include <Eigen/Geometry>
#include <tbb/parallel_for.h>
#include <pcl/recognition/cg/geometric_consistency.h>
// Instantiated here: the precompiled one lives in libpcl_recognition, which pulls in pcl_io and VTK.
#include <pcl/recognition/impl/cg/geometric_consistency.hpp>
#include <pcl/registration/ia_ransac.h>
#include <pcl/registration/sample_consensus_prerejective.h>
// Instantiated here, not loaded from libpcl_sample_consensus (see prepare_pcl.cpp).
#include <pcl/sample_consensus/impl/ransac.hpp>

#include "prepared_map_impl.hpp"

namespace mapmerge::align {
namespace {

template <class Feature>
std::vector<Match> match_features(const pcl::PointCloud<Feature>& src_f,
                                  const SerialKdTree<Feature>& src_tree,
                                  const SerialKdTree<Feature>& tgt_tree,
                                  const MatchConfig& c) {
  std::vector<Match> matches;
  const int k = c.mutual ? 1 : c.k_nearest;
  pcl::Indices idx(k);
  std::vector<float> d2(k);
  pcl::Indices back(1);
  std::vector<float> back_d2(1);
  for (std::size_t i = 0; i < src_f.size(); ++i) {
    const int found = tgt_tree.nearestKSearch(src_f[i], k, idx, d2);
    for (int n = 0; n < found; ++n) {
      if (c.mutual) {
        const auto& tgt_f = *tgt_tree.getInputCloud();
        if (src_tree.nearestKSearch(tgt_f[idx[n]], 1, back, back_d2) < 1 ||
            back[0] != static_cast<int>(i))
          continue;
      }
      matches.push_back({static_cast<int>(i), idx[n], d2[n]});
    }
  }
  std::sort(matches.begin(), matches.end(),
            [](const Match& a, const Match& b) { return a.distance < b.distance; });
  if (matches.size() > c.max_correspondences) matches.resize(c.max_correspondences);
  return matches;
}

/// Correspondences (source, target positions) usable by the geometric methods.
struct Pairs {
  std::vector<Eigen::Vector3d> src, tgt;
  std::vector<int> src_kp, tgt_kp;  ///< keypoint indices
  /// The same positions, one array per coordinate: the consensus count runs over all pairs for
  /// every sampled triple, and this layout lets the compiler vectorise it.
  std::array<std::vector<double>, 3> s, t;

  void add(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
    src.push_back(a);
    tgt.push_back(b);
    for (int k = 0; k < 3; ++k) {
      s[k].push_back(a[k]);
      t[k].push_back(b[k]);
    }
  }
};

Pairs pairs_of(const PreparedMap::Impl& target, const PreparedMap::Impl& source,
               const std::vector<Match>& matches, const std::vector<int>& subset) {
  std::vector<char> in_subset(source.keypoints->size(), 0);
  for (int i : subset) in_subset[static_cast<std::size_t>(i)] = 1;
  Pairs p;
  for (const Match& m : matches) {
    if (!in_subset[static_cast<std::size_t>(m.source)]) continue;
    p.add((*source.keypoints)[m.source].getVector3fMap().cast<double>(),
          (*target.keypoints)[m.target].getVector3fMap().cast<double>());
    p.src_kp.push_back(m.source);
    p.tgt_kp.push_back(m.target);
  }
  return p;
}

/// Rigid transform (least squares, Umeyama) from the listed pairs.
Eigen::Matrix4d fit(const Pairs& p, const std::vector<int>& which) {
  Eigen::Matrix3Xd a(3, which.size()), b(3, which.size());
  for (std::size_t i = 0; i < which.size(); ++i) {
    a.col(static_cast<Eigen::Index>(i)) = p.src[static_cast<std::size_t>(which[i])];
    b.col(static_cast<Eigen::Index>(i)) = p.tgt[static_cast<std::size_t>(which[i])];
  }
  return Eigen::umeyama(a, b, false);
}

/// Calls f(i, squared residual) for every pair under T (one pass over the coordinate arrays).
template <class F>
void for_each_residual(const Pairs& p, const Eigen::Matrix4d& T, F&& f) {
  const std::size_t n = p.s[0].size();
  const double *sx = p.s[0].data(), *sy = p.s[1].data(), *sz = p.s[2].data();
  const double *tx = p.t[0].data(), *ty = p.t[1].data(), *tz = p.t[2].data();
  const double r00 = T(0, 0), r01 = T(0, 1), r02 = T(0, 2), r10 = T(1, 0), r11 = T(1, 1), r12 = T(1, 2);
  const double r20 = T(2, 0), r21 = T(2, 1), r22 = T(2, 2), t0 = T(0, 3), t1 = T(1, 3), t2 = T(2, 3);
  for (std::size_t i = 0; i < n; ++i) {
    const double dx = r00 * sx[i] + r01 * sy[i] + r02 * sz[i] + t0 - tx[i];
    const double dy = r10 * sx[i] + r11 * sy[i] + r12 * sz[i] + t1 - ty[i];
    const double dz = r20 * sx[i] + r21 * sy[i] + r22 * sz[i] + t2 - tz[i];
    f(i, dx * dx + dy * dy + dz * dz);
  }
}

/// How many pairs T maps within eps of their partner: consensus_of(p, T, eps).size(), without
/// building the list.
std::size_t consensus_count(const Pairs& p, const Eigen::Matrix4d& T, double eps) {
  const double eps2 = eps * eps;
  double count = 0.0;  // a double sum (exact below 2^53) is what GCC vectorises here
  for_each_residual(p, T, [&](std::size_t, double d2) { count += d2 < eps2 ? 1.0 : 0.0; });
  return static_cast<std::size_t>(count);
}

/// The pairs T maps within eps of their partner, in index order.
std::vector<int> consensus_of(const Pairs& p, const Eigen::Matrix4d& T, double eps) {
  const double eps2 = eps * eps;
  std::vector<int> inliers(p.src.size());
  std::size_t k = 0;
  for_each_residual(p, T, [&](std::size_t i, double d2) {
    inliers[k] = static_cast<int>(i);  // written always, kept when within eps (no branch)
    k += d2 < eps2 ? 1 : 0;
  });
  inliers.resize(k);
  return inliers;
}

/// Consensus sets already fitted: sampled triples of one correct transform mostly give the
/// same set, and the same set gives the same least-squares transform and score again.
class SeenSets {
 public:
  /// True the first time `set` is offered.
  bool first(const std::vector<int>& set) { return seen_.insert(set).second; }

 private:
  struct Hash {
    std::size_t operator()(const std::vector<int>& v) const {
      std::uint64_t h = 1469598103934665603ULL;  // FNV-1a over the indices
      for (int i : v) h = (h ^ static_cast<std::uint32_t>(i)) * 1099511628211ULL;
      return static_cast<std::size_t>(h);
    }
  };
  std::unordered_set<std::vector<int>, Hash> seen_;
};

/// Sampled triples of correspondences, tried in batches: each triple's fit and consensus set,
/// and each new set's least-squares fit and score, are computed on all cores, then kept in the
/// order the triples were drawn. The hypotheses are those of trying them one after another.
class Trials {
 public:
  /// `keep(T, consensus)` receives each hypothesis (a consensus set seen the first time).
  Trials(const Pairs& p, double tol, std::size_t min_consensus, SeenSets& seen)
      : p_(p), tol_(tol), min_consensus_(min_consensus), seen_(seen) {}

  /// Adds a triple; tries the batch when it is full.
  template <class Keep>
  void add(const std::array<int, 3>& triple, Keep&& keep) {
    triples_.push_back(triple);
    if (triples_.size() >= kBatch) flush(keep);
  }

  /// Tries the triples added so far.
  template <class Keep>
  void flush(Keep&& keep) {
    const std::size_t n = triples_.size();
    sets_.resize(n);
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, n, 8), [&](const tbb::blocked_range<std::size_t>& r) {
      for (std::size_t i = r.begin(); i < r.end(); ++i) {
        const std::array<int, 3>& t = triples_[i];
        sets_[i] = consensus_of(p_, fit(p_, {t[0], t[1], t[2]}), tol_);
      }
    });
    fresh_.clear();
    for (std::size_t i = 0; i < n; ++i) {
      if (sets_[i].size() >= min_consensus_ && seen_.first(sets_[i])) fresh_.push_back(i);
    }
    fitted_.resize(fresh_.size());
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, fresh_.size(), 4), [&](const tbb::blocked_range<std::size_t>& r) {
      for (std::size_t k = r.begin(); k < r.end(); ++k) {
        const Eigen::Matrix4d T_ls = fit(p_, sets_[fresh_[k]]);  // least squares over the consensus
        fitted_[k] = {T_ls, consensus_count(p_, T_ls, tol_)};
      }
    });
    for (const auto& [T, consensus] : fitted_) keep(T, consensus);
    triples_.clear();
  }

 private:
  static constexpr std::size_t kBatch = 256;
  const Pairs& p_;
  double tol_;
  std::size_t min_consensus_;
  SeenSets& seen_;
  std::vector<std::array<int, 3>> triples_;
  std::vector<std::vector<int>> sets_;
  std::vector<std::size_t> fresh_;
  std::vector<std::pair<Eigen::Matrix4d, std::size_t>> fitted_;
};

/// Keeps the `max` best distinct hypotheses (by consensus).
void keep_best(std::vector<Hypothesis>& best, Hypothesis h, std::size_t max, double rot,
               double trans) {
  // A full list whose every entry has more consensus keeps none of h: it can replace no
  // duplicate of itself and would be the one dropped.
  if (best.size() >= max && !best.empty() && h.consensus < best.back().consensus) return;
  for (auto& b : best) {
    if (same_pose(b.T_target_source, h.T_target_source, rot, trans)) {
      if (h.consensus > b.consensus) b = h;
      return;
    }
  }
  best.push_back(h);
  std::sort(best.begin(), best.end(),
            [](const Hypothesis& a, const Hypothesis& b) { return a.consensus > b.consensus; });
  if (best.size() > max) best.resize(max);
}

/// Deterministic seeds from second-order compatibility: the correct correspondences are all
/// compatible with each other, so a pair of correct ones shares every other correct one as a
/// common compatible partner, while a chance pair shares only a few. The `count` pairs with the
/// most common partners each give one hypothesis per common partner (a triple), scored by
/// consensus like the RANSAC samples. Finds the true transform when only ~5-10 of thousands of
/// correspondences are correct, where uniform sampling rarely draws three of them.
template <class Keep>
void seed_from_common_partners(const Pairs& p, const std::vector<std::vector<int>>& compatible,
                               const MatchConfig& c, Trials& trials, Keep&& keep) {
  const std::size_t m = p.src.size(), words = (m + 63) / 64;
  if (c.seed_pairs == 0) return;
  std::vector<std::uint64_t> bits(m * words, 0);
  for (std::size_t i = 0; i < m; ++i)
    for (int j : compatible[i]) bits[i * words + static_cast<std::size_t>(j) / 64] |= 1ULL << (j % 64);
  struct Edge {
    int common, i, j;
  };
  std::vector<Edge> edges;
  for (std::size_t i = 0; i < m; ++i)
    for (int j : compatible[i]) {
      if (static_cast<std::size_t>(j) <= i) continue;
      int common = 0;
      for (std::size_t w = 0; w < words; ++w)
        common += __builtin_popcountll(bits[i * words + w] & bits[static_cast<std::size_t>(j) * words + w]);
      if (common >= 1) edges.push_back({common, static_cast<int>(i), j});
    }
  const std::size_t n = std::min(edges.size(), c.seed_pairs);
  std::partial_sort(edges.begin(), edges.begin() + static_cast<std::ptrdiff_t>(n), edges.end(),
                    [](const Edge& a, const Edge& b) { return a.common > b.common; });
  for (std::size_t e = 0; e < n; ++e) {
    const auto a = static_cast<std::size_t>(edges[e].i), b = static_cast<std::size_t>(edges[e].j);
    for (std::size_t w = 0; w < words; ++w) {
      std::uint64_t both = bits[a * words + w] & bits[b * words + w];
      while (both != 0) {
        const int k = static_cast<int>(w * 64) + __builtin_ctzll(both);
        both &= both - 1;
        trials.add({edges[e].i, edges[e].j, k}, keep);
      }
    }
  }
  trials.flush(keep);
}

/// RANSAC guided by pairwise length consistency: a seed correspondence and two partners that
/// preserve distances to it (and to each other) are drawn; prerejection by edge similarity.
std::vector<Hypothesis> ransac(const Pairs& p, const AlignConfig& cfg, double res, unsigned seed) {
  const MatchConfig& c = cfg.match;
  const std::size_t m = p.src.size();
  if (m < 3) return {};
  const double tol = c.inlier_distance * res;
  const double min_edge = c.min_edge * res;
  // Compatibility lists: j is compatible with i when both lengths agree within tol.
  std::vector<std::vector<int>> compatible(m);
  for (std::size_t i = 0; i < m; ++i)
    for (std::size_t j = i + 1; j < m; ++j) {
      const double ds = (p.src[i] - p.src[j]).norm();
      const double dt = (p.tgt[i] - p.tgt[j]).norm();
      if (ds < min_edge || std::abs(ds - dt) > tol) continue;
      if (std::min(ds, dt) < c.edge_similarity * std::max(ds, dt)) continue;
      compatible[i].push_back(static_cast<int>(j));
      compatible[j].push_back(static_cast<int>(i));
    }
  std::vector<double> weight(m);
  for (std::size_t i = 0; i < m; ++i) weight[i] = static_cast<double>(compatible[i].size());
  if (*std::max_element(weight.begin(), weight.end()) < 2.0) return {};
  std::vector<Hypothesis> best;
  const double rot = cfg.validate.distinct_rotation_deg;
  const double trans = cfg.validate.distinct_translation * res;
  SeenSets seen;
  Trials trials(p, tol, c.min_consensus, seen);
  const auto keep = [&](const Eigen::Matrix4d& T, std::size_t n) {
    keep_best(best, {T, n, -1}, c.max_hypotheses, rot, trans);
  };
  seed_from_common_partners(p, compatible, c, trials, keep);
  std::mt19937 rng(seed);
  std::discrete_distribution<std::size_t> pick_seed(weight.begin(), weight.end());
  for (int it = 0; it < c.iterations; ++it) {
    const std::size_t a = pick_seed(rng);
    const auto& na = compatible[a];
    if (na.size() < 2) continue;
    std::uniform_int_distribution<std::size_t> pick(0, na.size() - 1);
    const int b = na[pick(rng)], cc = na[pick(rng)];
    if (b == cc) continue;
    const auto& nb = compatible[static_cast<std::size_t>(b)];
    if (!std::binary_search(nb.begin(), nb.end(), cc)) continue;  // lists are sorted
    trials.add({static_cast<int>(a), b, cc}, keep);
  }
  trials.flush(keep);
  return best;
}

/// Subset of keypoints and features for PCL's registration classes.
template <class Feature>
void subset_clouds(const PreparedMap::Impl& m, const pcl::PointCloud<Feature>& f,
                   const std::vector<int>& subset, Cloud& points,
                   pcl::PointCloud<Feature>& features) {
  for (int i : subset) {
    points.push_back((*m.keypoints)[i]);
    features.push_back(f[i]);
  }
}

template <class Feature>
std::vector<Hypothesis> pcl_sac(const PreparedMap::Impl& target, const PreparedMap::Impl& source,
                                const pcl::PointCloud<Feature>& tgt_f,
                                const pcl::PointCloud<Feature>& src_f,
                                const std::vector<int>& subset, const AlignConfig& cfg,
                                double res) {
  const MatchConfig& c = cfg.match;
  auto src = std::make_shared<Cloud>();
  auto src_feat = std::make_shared<pcl::PointCloud<Feature>>();
  subset_clouds(source, src_f, subset, *src, *src_feat);
  if (src->size() < 3 || target.keypoints->size() < 3) return {};
  auto tgt_feat = std::make_shared<const pcl::PointCloud<Feature>>(tgt_f);
  Cloud aligned;
  Eigen::Matrix4f T = Eigen::Matrix4f::Identity();
  bool converged = false;
  if (c.method == MatchMethod::kSacIa) {
    pcl::SampleConsensusInitialAlignment<Point, Point, Feature> sac;
    sac.setInputSource(src);
    sac.setSourceFeatures(src_feat);
    sac.setInputTarget(target.keypoints);
    sac.setTargetFeatures(tgt_feat);
    sac.setMinSampleDistance(static_cast<float>(c.min_edge * res));
    sac.setMaxCorrespondenceDistance(c.inlier_distance * res);
    sac.setMaximumIterations(c.iterations);
    sac.setCorrespondenceRandomness(c.k_nearest);
    sac.align(aligned);
    converged = sac.hasConverged();
    T = sac.getFinalTransformation();
  } else {
    pcl::SampleConsensusPrerejective<Point, Point, Feature> sac;
    sac.setInputSource(src);
    sac.setSourceFeatures(src_feat);
    sac.setInputTarget(target.keypoints);
    sac.setTargetFeatures(tgt_feat);
    sac.setMaximumIterations(c.iterations);
    sac.setNumberOfSamples(3);
    sac.setCorrespondenceRandomness(c.k_nearest);
    sac.setSimilarityThreshold(static_cast<float>(c.edge_similarity));
    sac.setMaxCorrespondenceDistance(c.inlier_distance * res);
    sac.setInlierFraction(0.05F);
    sac.align(aligned);
    converged = sac.hasConverged();
    T = sac.getFinalTransformation();
  }
  if (!converged) return {};
  return {{T.cast<double>(), 0, -1}};
}

std::vector<Hypothesis> gcc(const PreparedMap::Impl& target, const Pairs& p,
                            const AlignConfig& cfg, double res) {
  auto model = std::make_shared<Cloud>();
  auto corrs = std::make_shared<pcl::Correspondences>();
  for (std::size_t i = 0; i < p.src.size(); ++i) {
    Point q;
    q.getVector3fMap() = p.src[i].cast<float>();
    model->push_back(q);
    corrs->emplace_back(static_cast<int>(i), p.tgt_kp[i], 0.0F);
  }
  if (corrs->size() < 3) return {};
  pcl::GeometricConsistencyGrouping<Point, Point> gc;
  gc.setGCSize(cfg.match.gc_size * res);
  gc.setGCThreshold(cfg.match.gc_threshold);
  gc.setInputCloud(model);
  gc.setSceneCloud(target.keypoints);
  gc.setModelSceneCorrespondences(corrs);
  std::vector<Eigen::Matrix4f, Eigen::aligned_allocator<Eigen::Matrix4f>> transforms;
  std::vector<pcl::Correspondences> clusters;
  gc.recognize(transforms, clusters);
  std::vector<Hypothesis> out;
  const double rot = cfg.validate.distinct_rotation_deg;
  const double trans = cfg.validate.distinct_translation * res;
  for (std::size_t i = 0; i < transforms.size(); ++i)
    keep_best(out, {transforms[i].cast<double>(), clusters[i].size(), -1},
              cfg.match.max_hypotheses, rot, trans);
  return out;
}

}  // namespace

std::vector<Match> match_descriptors(const PreparedMap::Impl& target,
                                     const PreparedMap::Impl& source, const MatchConfig& config) {
  if (source.fpfh && target.fpfh && !source.fpfh->empty() && !target.fpfh->empty())
    return match_features(*source.fpfh, *source.fpfh_tree, *target.fpfh_tree, config);
  if (source.shot && target.shot && !source.shot->empty() && !target.shot->empty())
    return match_features(*source.shot, *source.shot_tree, *target.shot_tree, config);
  return {};
}

std::vector<Hypothesis> generate_hypotheses(const PreparedMap::Impl& target,
                                            const PreparedMap::Impl& source,
                                            const std::vector<Match>& matches,
                                            const std::vector<int>& subset,
                                            const AlignConfig& config, unsigned seed) {
  // Lengths of this stage are in feature units (config.hpp).
  const double res = length_units(std::max(target.resolution, source.resolution), config).feature;
  switch (config.match.method) {
    case MatchMethod::kRansac:
      return ransac(pairs_of(target, source, matches, subset), config, res, seed);
    case MatchMethod::kGcc:
      return gcc(target, pairs_of(target, source, matches, subset), config, res);
    case MatchMethod::kSacIa:
    case MatchMethod::kPrerejective:
      if (source.fpfh && target.fpfh)
        return pcl_sac(target, source, *target.fpfh, *source.fpfh, subset, config, res);
      if (source.shot && target.shot)
        return pcl_sac(target, source, *target.shot, *source.shot, subset, config, res);
      return {};
  }
  return {};
}

}  // namespace mapmerge::align
