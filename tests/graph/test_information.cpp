// information_from_alignment: the documented noise model, its monotonicity and its pivot.
#include <gtest/gtest.h>

#include <cmath>
#include <limits>

#include <Eigen/Cholesky>
#include <Eigen/LU>

#include "mapmerge/graph/information.hpp"

namespace mg = mapmerge::graph;

namespace {

mg::AlignmentQuality good() {
  mg::AlignmentQuality q;
  q.inliers = 2000;
  q.fitness = 0.02;
  q.overlap = 0.3;
  return q;
}

double translation_info(const mg::EdgeInformation& e) { return e.information(0, 0); }
double rotation_info(const mg::EdgeInformation& e) { return e.information(5, 5); }

}  // namespace

TEST(GraphInformation, AtTheReferenceNumbersSigmaIsTheFitness) {
  const mg::EdgeInformation e = mg::information_from_alignment(good());
  ASSERT_TRUE(e.valid) << e.reason;
  EXPECT_NEAR(e.sigma_translation, 0.02, 1e-12);
  EXPECT_NEAR(e.sigma_rotation, 0.02 / 3.0, 1e-12);
  EXPECT_NEAR(e.information(0, 0), 1.0 / (0.02 * 0.02), 1e-6);
  EXPECT_NEAR(e.information(3, 3), 9.0 / (0.02 * 0.02), 1e-6);
  EXPECT_EQ(Eigen::LLT<mg::Matrix6d>(e.information).info(), Eigen::Success);
}

TEST(GraphInformation, MoreInliersLessFitnessMoreOverlapMeanMoreInformation) {
  const mg::EdgeInformation base = mg::information_from_alignment(good());
  auto q = good();
  q.inliers = 6000;
  EXPECT_GT(translation_info(mg::information_from_alignment(q)), translation_info(base));
  q = good();
  q.fitness = 0.04;
  EXPECT_LT(translation_info(mg::information_from_alignment(q)), translation_info(base));
  q = good();
  q.overlap = 0.05;
  EXPECT_LT(rotation_info(mg::information_from_alignment(q)), rotation_info(base));
}

TEST(GraphInformation, GainsSaturate) {
  auto q = good();
  q.inliers = 8000;  // max_inlier_gain 4 x reference
  const double at_cap = translation_info(mg::information_from_alignment(q));
  q.inliers = 800000;
  EXPECT_DOUBLE_EQ(translation_info(mg::information_from_alignment(q)), at_cap);
  q = good();
  q.fitness = 0.0;  // floor min_fitness
  EXPECT_NEAR(mg::information_from_alignment(q).sigma_translation, 0.01, 1e-12);
  q.overlap = 0.9;  // no bonus beyond reference_overlap
  EXPECT_NEAR(mg::information_from_alignment(q).sigma_translation, 0.01, 1e-12);
}

TEST(GraphInformation, PivotCouplesRotationIntoTranslationAtTheOrigin) {
  auto q = good();
  q.pivot_source = Eigen::Vector3d(10.0, 0.0, 0.0);
  const mg::EdgeInformation e = mg::information_from_alignment(q);
  ASSERT_TRUE(e.valid);
  const mg::Matrix6d cov = e.information.inverse();
  // A yaw error at x = 10 m moves the origin along y by 10 m * sigma_r.
  const double sr = e.sigma_rotation;
  const double st = e.sigma_translation;
  EXPECT_NEAR(cov(1, 1), st * st + 100.0 * sr * sr, 1e-9);
  EXPECT_NEAR(cov(0, 0), st * st, 1e-9);  // along the lever arm: no coupling
  EXPECT_NEAR(cov(5, 5), sr * sr, 1e-12);
  EXPECT_GT(std::abs(cov(1, 5)), 0.0);
}

TEST(GraphInformation, UnusableInputsAreAValueNotAnException) {
  auto q = good();
  q.inliers = 0;
  EXPECT_FALSE(mg::information_from_alignment(q).valid);
  q = good();
  q.fitness = std::numeric_limits<double>::infinity();
  const mg::EdgeInformation e = mg::information_from_alignment(q);
  EXPECT_FALSE(e.valid);
  EXPECT_FALSE(e.reason.empty());
  EXPECT_TRUE(e.information.isZero());
  mg::InformationConfig bad;
  bad.lever_arm = 0.0;
  EXPECT_FALSE(mg::information_from_alignment(good(), bad).valid);
}

TEST(GraphInformation, OverlapPivotIsTheCentreOfTheSharedBox) {
  const Eigen::AlignedBox3d source(Eigen::Vector3d(0, 0, 0), Eigen::Vector3d(10, 4, 2));
  const Eigen::AlignedBox3d target(Eigen::Vector3d(0, 0, 0), Eigen::Vector3d(10, 4, 2));
  Eigen::Isometry3d T_target_source = Eigen::Isometry3d::Identity();
  T_target_source.translation() = Eigen::Vector3d(-6, 0, 0);  // source x = 6 is target x = 0
  const Eigen::Vector3d pivot = mg::overlap_pivot(source, target, T_target_source);
  // The target covers source x in [6, 16]: shared x in [6, 10].
  EXPECT_TRUE(pivot.isApprox(Eigen::Vector3d(8, 2, 1))) << pivot.transpose();
  T_target_source.translation() = Eigen::Vector3d(-50, 0, 0);
  EXPECT_TRUE(mg::overlap_pivot(source, target, T_target_source).isApprox(source.center()));
}
