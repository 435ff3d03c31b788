// SerialKdTree (core/align/src/serial_kd_tree.hpp) against pcl::KdTreeFLANN, the tree it
// replaces: on a real map's points it must return the same neighbours, in the same order, with
// the same squared distances, for every kind of query the pipeline and PCL's estimators make.
#include <algorithm>
#include <cmath>
#include <limits>
#include <memory>
#include <string>

#include <gtest/gtest.h>

#include <pcl/kdtree/kdtree_flann.h>

#include "mapmerge/align/stages.hpp"
#include "mapmerge/map/map_io.hpp"
#include "serial_kd_tree.hpp"

namespace ma = mapmerge::align;
using Point = pcl::PointXYZINormal;
using Cloud = pcl::PointCloud<Point>;

namespace {

/// geb079's occupied voxel centres, with a NaN point every 101st (a tree must skip those).
Cloud::Ptr map_cloud(double* resolution) {
  const auto tree = mapmerge::read_octree_file(std::string(MAPMERGE_DATA_DIR) + "/geb079.bt");
  *resolution = tree->getResolution();
  auto cloud = std::make_shared<Cloud>();
  for (const auto& p : ma::to_points(*tree, {})) {
    Point q;
    q.getVector3fMap() = p.position;
    q.intensity = p.occupancy;
    if (cloud->size() % 101 == 50) {
      Point bad = q;
      bad.x = std::numeric_limits<float>::quiet_NaN();
      cloud->push_back(bad);
    }
    cloud->push_back(q);
  }
  return cloud;
}

struct Result {
  int n = 0;
  pcl::Indices idx;
  std::vector<float> d2;
};

void expect_same(const Result& ours, const Result& pcls, std::size_t query) {
  ASSERT_EQ(ours.n, pcls.n) << "query " << query;
  ASSERT_EQ(ours.idx, pcls.idx) << "query " << query;
  ASSERT_EQ(ours.d2, pcls.d2) << "query " << query;
}

class KdTree : public ::testing::Test {
 protected:
  void SetUp() override { cloud_ = map_cloud(&res_); }
  Cloud::Ptr cloud_;
  double res_ = 0.0;
};

}  // namespace

TEST_F(KdTree, SameNeighboursAsPclOnARealMap) {
  ASSERT_GT(cloud_->size(), 10000U);
  ma::SerialKdTree<Point> ours(true);  // sorted radius results, as KdTreeFLANN by default
  ours.setInputCloud(cloud_);
  pcl::KdTreeFLANN<Point> pcls;
  pcls.setInputCloud(cloud_);
  std::size_t finite = 0;
  for (const auto& p : *cloud_) finite += std::isfinite(p.x) ? 1 : 0;
  ASSERT_LT(finite, cloud_->size());  // the cloud does hold NaN points
  EXPECT_EQ(ours.size(), finite);
  std::size_t neighbours = 0;
  for (std::size_t i = 0; i < cloud_->size(); i += 37) {
    const Point& p = (*cloud_)[i];
    if (!std::isfinite(p.x)) continue;
    // A query off the grid too, so that distances tie less often than between voxel centres.
    Point off = p;
    off.x += static_cast<float>(0.3 * res_);
    off.z -= static_cast<float>(0.2 * res_);
    for (const Point& q : {p, off}) {
      for (int k : {1, 8, 300}) {  // 300: flann's heap result set
        Result a, b;
        a.n = ours.nearestKSearch(q, k, a.idx, a.d2);
        b.n = pcls.nearestKSearch(q, static_cast<unsigned>(k), b.idx, b.d2);
        expect_same(a, b, i);
      }
      for (unsigned max_nn : {0U, 1U, 5U}) {
        Result a, b;
        a.n = ours.radiusSearch(q, 3.0 * res_, a.idx, a.d2, max_nn);
        b.n = pcls.radiusSearch(q, 3.0 * res_, b.idx, b.d2, max_nn);
        expect_same(a, b, i);
        neighbours += static_cast<std::size_t>(a.n);
      }
    }
  }
  EXPECT_GT(neighbours, 10000U);  // the radius queries found real neighbourhoods
}

TEST_F(KdTree, UnsortedAndSubsetQueriesMatchPcl) {
  auto subset = std::make_shared<pcl::Indices>();
  for (std::size_t i = 0; i < cloud_->size(); i += 3) subset->push_back(static_cast<pcl::index_t>(i));
  ma::SerialKdTree<Point> ours;  // unsorted by default
  ours.setInputCloud(cloud_, subset);
  pcl::KdTreeFLANN<Point> pcls(false);
  pcls.setInputCloud(cloud_, subset);
  for (std::size_t i = 1; i < cloud_->size(); i += 53) {
    const Point& p = (*cloud_)[i];
    if (!std::isfinite(p.x)) continue;
    Result a, b;
    a.n = ours.radiusSearch(p, 4.0 * res_, a.idx, a.d2);
    b.n = pcls.radiusSearch(p, 4.0 * res_, b.idx, b.d2);
    expect_same(a, b, i);
    for (pcl::index_t j : a.idx) ASSERT_EQ(j % 3, 0) << "a neighbour outside the subset";
    a.n = ours.nearestKSearch(p, 4, a.idx, a.d2);
    b.n = pcls.nearestKSearch(p, 4, b.idx, b.d2);
    expect_same(a, b, i);
  }
}

TEST_F(KdTree, ANewCloudReplacesTheIndexedOne) {
  ma::SerialKdTree<Point> tree;
  tree.setInputCloud(cloud_);
  auto moved = std::make_shared<Cloud>(*cloud_);
  for (auto& p : *moved) p.x += 100.0F;
  const Point& probe = (*cloud_)[0];
  pcl::Indices idx;
  std::vector<float> d2;
  ASSERT_EQ(tree.nearestKSearch(probe, 1, idx, d2), 1);
  EXPECT_EQ(d2[0], 0.0F);
  tree.setInputCloud(moved);  // another cloud object: indexed anew
  ASSERT_EQ(tree.nearestKSearch(probe, 1, idx, d2), 1);
  float nearest = std::numeric_limits<float>::infinity();  // by brute force
  for (const auto& p : *moved)
    if (std::isfinite(p.x)) nearest = std::min(nearest, (p.getVector3fMap() - probe.getVector3fMap()).squaredNorm());
  EXPECT_GT(nearest, 1.0F);
  EXPECT_FLOAT_EQ(d2[0], nearest);
  EXPECT_EQ(tree.radiusSearch(probe, 0.5, idx, d2), 0);
  Cloud::Ptr empty = std::make_shared<Cloud>();
  tree.setInputCloud(empty);
  EXPECT_EQ(tree.size(), 0U);
  EXPECT_EQ(tree.nearestKSearch(probe, 3, idx, d2), 0);
  EXPECT_EQ(tree.radiusSearch(probe, 1.0, idx, d2), 0);
}
