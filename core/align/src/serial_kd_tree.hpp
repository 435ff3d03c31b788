#pragma once
/// Internal: the kd-tree behind every neighbour query of the pipeline, ours and PCL's.
///
/// pcl::KdTreeFLANN (and pcl::search::KdTree, which wraps it) sends each single-point query
/// through flann::Index::knnSearch / radiusSearch, whose body is an OpenMP parallel region even
/// with one thread; libgomp ends every region with barrier wake-ups that are system calls. The
/// paper pair made 753k futex calls, and ~40 % of a merge's CPU time was spent in the kernel.
/// This tree is FLANN's same single kd-tree (leaves of 15 points, exact search) queried directly
/// on the calling thread, so it returns the same neighbours in the same order without them.
/// It derives from pcl::search::Search so PCL's estimators take it with setSearchMethod.

#include <algorithm>
#include <cstddef>
#include <memory>
#include <string>
#include <vector>

#include <flann/algorithms/dist.h>
#include <flann/algorithms/kdtree_single_index.h>
#include <flann/util/result_set.h>
#include <pcl/point_representation.h>
#include <pcl/search/search.h>

namespace mapmerge::align {

template <class PointT>
class SerialKdTree final : public pcl::search::Search<PointT> {
  using Base = pcl::search::Search<PointT>;

 public:
  using Ptr = std::shared_ptr<SerialKdTree>;
  using ConstPtr = std::shared_ptr<const SerialKdTree>;
  using typename Base::IndicesConstPtr;
  using typename Base::PointCloudConstPtr;
  using Base::nearestKSearch;
  using Base::radiusSearch;

  /// `sorted`: radius results by increasing distance (k-nearest results always are). No
  /// consumer in the pipeline needs that order, so the default is the tree's own visiting order,
  /// as in the pcl::search::KdTree(false) that PCL's estimators build for themselves.
  explicit SerialKdTree(bool sorted = false) : Base("SerialKdTree", sorted) {}

  /// Indexes the valid points of `cloud` (of `indices` when given); results are indices into
  /// `cloud`. Giving the cloud and indices it already indexes keeps the tree (PCL's estimators
  /// hand their search surface over again): give a new cloud object when points have moved.
  void setInputCloud(const PointCloudConstPtr& cloud,
                     const IndicesConstPtr& indices = IndicesConstPtr()) override {
    if (index_ && cloud == this->input_ && indices == this->indices_) return;
    this->input_ = cloud;
    this->indices_ = indices;
    index_.reset();
    ids_.clear();
    size_ = 0;
    if (!cloud) return;
    const std::size_t n = indices ? indices->size() : cloud->size();
    std::vector<float> data;  // the build's input; the index keeps its own copy (below)
    data.reserve(n * static_cast<std::size_t>(dim_));
    ids_.reserve(n);
    bool identity = true;
    for (std::size_t k = 0; k < n; ++k) {
      const auto i = indices ? (*indices)[k] : static_cast<pcl::index_t>(k);
      const PointT& p = (*cloud)[static_cast<std::size_t>(i)];
      if (!repr_.isValid(p)) continue;
      identity &= static_cast<std::size_t>(i) == ids_.size();
      ids_.push_back(i);
      data.resize(data.size() + static_cast<std::size_t>(dim_));
      float* out = data.data() + data.size() - static_cast<std::size_t>(dim_);
      repr_.vectorize(p, out);
    }
    size_ = ids_.size();
    if (identity) std::vector<pcl::index_t>().swap(ids_);  // tree index == cloud index
    if (size_ == 0) return;
    // With `reorder`, the index copies the points in its leaves' order and searches that copy
    // only (KDTreeSingleIndex::searchLevel); the input is read by the build alone, so it is let
    // go of here: a cloud's tree holds one copy of its points, not two (12 B a point of 3D).
    index_ = std::make_unique<Index>(flann::Matrix<float>(data.data(), size_, static_cast<std::size_t>(dim_)),
                                     flann::KDTreeSingleIndexParams(15, /*reorder=*/true));
    index_->buildIndex();
  }

  /// The min(k, size) nearest points, nearest first; returns how many.
  int nearestKSearch(const PointT& point, int k, pcl::Indices& k_indices,
                     std::vector<float>& k_sqr_distances) const override {
    const std::size_t n = std::min(static_cast<std::size_t>(std::max(k, 0)), size_);
    k_indices.resize(n);
    k_sqr_distances.resize(n);
    if (n == 0) return 0;
    Query q(*this, point);
    if (n > kHeapThreshold) {  // as flann::Index::knnSearch chooses
      flann::KNNResultSet2<float> result(n);
      return search(result, q, n, true, k_indices, k_sqr_distances);
    }
    flann::KNNSimpleResultSet<float> result(n);
    return search(result, q, n, true, k_indices, k_sqr_distances);
  }

  /// The points closer than `radius` [m]; with `max_nn` > 0 only the nearest `max_nn` of them.
  int radiusSearch(const PointT& point, double radius, pcl::Indices& k_indices,
                   std::vector<float>& k_sqr_distances, unsigned int max_nn = 0) const override {
    k_indices.clear();
    k_sqr_distances.clear();
    if (size_ == 0) return 0;
    const auto r2 = static_cast<float>(radius * radius);
    Query q(*this, point);
    if (max_nn == 0 || max_nn >= size_) {
      thread_local std::vector<flann::DistanceIndex<float>> hits;  // reused: no allocation a query
      hits.clear();
      Within result(r2, hits);
      index_->findNeighbors(result, q.data(), params_);
      if (this->sorted_results_) std::sort(hits.begin(), hits.end());
      k_indices.reserve(hits.size());
      k_sqr_distances.reserve(hits.size());
      for (const auto& h : hits) {
        k_indices.push_back(cloud_index(h.index_));
        k_sqr_distances.push_back(h.dist_);
      }
      return static_cast<int>(k_indices.size());
    }
    flann::KNNRadiusResultSet<float> result(r2, max_nn);
    return search(result, q, max_nn, this->sorted_results_, k_indices, k_sqr_distances);
  }

  std::size_t size() const { return size_; }

 private:
  using Index = flann::KDTreeSingleIndex<flann::L2_Simple<float>>;
  static constexpr std::size_t kHeapThreshold = 250;  // flann's KNN_HEAP_THRESHOLD
  pcl::index_t cloud_index(std::size_t tree_index) const {
    return ids_.empty() ? static_cast<pcl::index_t>(tree_index) : ids_[tree_index];
  }

  class Query;

  /// Runs one query into a FLANN result set holding at most `capacity` and copies out what it
  /// found as cloud indices; returns how many.
  template <class ResultSet>
  int search(ResultSet& result, Query& q, std::size_t capacity, bool sorted, pcl::Indices& k_indices,
             std::vector<float>& k_sqr_distances) const {
    std::vector<std::size_t> found(capacity);
    index_->findNeighbors(result, q.data(), params_);
    const std::size_t n = std::min(result.size(), capacity);
    k_sqr_distances.resize(n);
    if (n > 0) result.copy(found.data(), k_sqr_distances.data(), n, sorted);
    k_indices.resize(n);
    for (std::size_t j = 0; j < n; ++j) k_indices[j] = cloud_index(found[j]);
    return static_cast<int>(n);
  }

  /// A point as the tree's vector (3 floats for positions, 33 for FPFH, 352 for SHOT).
  class Query {
   public:
    Query(const SerialKdTree& tree, const PointT& p) {
      if (tree.dim_ > kInline) heap_.resize(static_cast<std::size_t>(tree.dim_));
      float* out = data();
      tree.repr_.vectorize(p, out);
    }
    float* data() { return heap_.empty() ? inline_ : heap_.data(); }

   private:
    static constexpr int kInline = 64;
    float inline_[kInline];
    std::vector<float> heap_;
  };

  /// Every point closer than sqrt(r2), in the order the tree visits them (flann's
  /// RadiusResultSet, into a buffer kept by the thread instead of 1024 entries a query).
  struct Within final : flann::ResultSet<float> {
    Within(float radius2, std::vector<flann::DistanceIndex<float>>& out) : r2(radius2), hits(out) {}
    bool full() const override { return true; }
    float worstDist() const override { return r2; }
    void addPoint(float dist, std::size_t index) override {
      if (dist < r2) hits.emplace_back(dist, index);
    }
    float r2;
    std::vector<flann::DistanceIndex<float>>& hits;
  };

  pcl::DefaultPointRepresentation<PointT> repr_;
  int dim_ = repr_.getNumberOfDimensions();
  flann::SearchParams params_{-1, 0.0F, true};  // exact search (eps 0), as pcl::KdTreeFLANN
  std::size_t size_ = 0;            ///< points indexed
  std::vector<pcl::index_t> ids_;  ///< tree index -> cloud index (empty: the same)
  std::unique_ptr<Index> index_;
};

}  // namespace mapmerge::align
