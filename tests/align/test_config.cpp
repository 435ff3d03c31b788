#include <gtest/gtest.h>

#include "mapmerge/align/config.hpp"

namespace ma = mapmerge::align;

TEST(AlignConfig, EmptyDocumentGivesDefaults) {
  const ma::AlignConfig c = ma::parse_align_config("");
  EXPECT_EQ(c.match.method, ma::MatchMethod::kRansac);
  EXPECT_DOUBLE_EQ(c.validate.d_th, ma::ValidateConfig{}.d_th);
}

TEST(AlignConfig, SetsEveryKindOfValue) {
  const ma::AlignConfig c = ma::parse_align_config(
      "seed: 7\n"
      "preprocess: {voxel_size: 3.5, remove_ground: true, z_min: -1, z_max: 2.5, pass_through: true}\n"
      "describe: {method: shot}\n"
      "match: {method: gcc, max_correspondences: 500}\n"
      "refine: {method: ndt}\n"
      "submodels: {enabled: true, block_size: 40}\n");
  EXPECT_EQ(c.seed, 7U);
  EXPECT_DOUBLE_EQ(c.preprocess.voxel_size, 3.5);
  EXPECT_TRUE(c.preprocess.remove_ground);
  EXPECT_DOUBLE_EQ(c.preprocess.z_max, 2.5);
  EXPECT_EQ(c.describe.method, ma::Descriptor::kShot);
  EXPECT_EQ(c.match.method, ma::MatchMethod::kGcc);
  EXPECT_EQ(c.match.max_correspondences, 500U);
  EXPECT_EQ(c.refine.method, ma::RefineMethod::kNdt);
  EXPECT_TRUE(c.submodels.enabled);
  EXPECT_DOUBLE_EQ(c.submodels.block_size, 40.0);
}

TEST(AlignConfig, UnknownKeysAreErrorsNamingTheKey) {
  try {
    ma::parse_align_config("match: {methd: gcc}\n");
    FAIL() << "unknown key accepted";
  } catch (const ma::ConfigError& e) {
    EXPECT_NE(std::string(e.what()).find("match.methd"), std::string::npos) << e.what();
  }
  EXPECT_THROW(ma::parse_align_config("matching: {method: gcc}\n"), ma::ConfigError);
  EXPECT_THROW(ma::parse_align_config("voxel_size: 3\n"), ma::ConfigError);
}

TEST(AlignConfig, BadValuesAreErrors) {
  EXPECT_THROW(ma::parse_align_config("match: {method: magic}\n"), ma::ConfigError);
  EXPECT_THROW(ma::parse_align_config("validate: {d_th: abc}\n"), ma::ConfigError);
  EXPECT_THROW(ma::parse_align_config("validate: {d_th: -1}\n"), ma::ConfigError);
  EXPECT_THROW(ma::parse_align_config("validate: {max_tilt_deg: 181}\n"), ma::ConfigError);
  EXPECT_THROW(ma::parse_align_config("validate: {max_pair_distance: -0.1}\n"), ma::ConfigError);
  EXPECT_THROW(ma::parse_align_config("validate: {max_near_conflict_share: 1.5}\n"), ma::ConfigError);
  EXPECT_EQ(ma::parse_align_config("validate: {max_near_conflict_share: 1}\n").validate.max_near_conflict_share, 1.0);
  EXPECT_EQ(ma::parse_align_config("validate: {max_tilt_deg: 180}\n").validate.max_tilt_deg, 180.0);
  EXPECT_THROW(ma::parse_align_config("[1, 2]\n"), ma::ConfigError);
  EXPECT_THROW(ma::parse_align_config("match: {method: [\n"), ma::ConfigError);
  EXPECT_THROW(ma::load_align_config("/nonexistent/align.yaml"), ma::ConfigError);
}

TEST(AlignConfig, YamlDumpRoundTrips) {
  ma::AlignConfig c;
  c.match.method = ma::MatchMethod::kPrerejective;
  c.refine.max_iterations = 17;
  c.refine.final_iterations = 41;
  c.preprocess.z_min = -0.5;
  const ma::AlignConfig back = ma::parse_align_config(ma::dump_align_config_yaml(c));
  EXPECT_EQ(back.match.method, ma::MatchMethod::kPrerejective);
  EXPECT_EQ(back.refine.max_iterations, 17);
  EXPECT_EQ(back.refine.final_iterations, 41);
  EXPECT_DOUBLE_EQ(back.preprocess.z_min, -0.5);
  EXPECT_EQ(ma::dump_align_config_yaml(back), ma::dump_align_config_yaml(c));
  EXPECT_NE(ma::dump_align_config_json(c).find("\"prerejective\""), std::string::npos);
}

TEST(AlignConfig, LengthUnitsAreMetricAndFlooredAtTheVoxel) {
  const ma::AlignConfig c;
  for (const double res : {0.02, 0.05}) {  // RGB-D and indoor maps: the same metric features
    const ma::LengthUnits u = ma::length_units(res, c);
    EXPECT_DOUBLE_EQ(u.res, res);
    EXPECT_DOUBLE_EQ(u.feature, 0.05);
    EXPECT_DOUBLE_EQ(u.preprocess, 0.05);
    EXPECT_DOUBLE_EQ(u.refine, 0.05);
  }
  const ma::LengthUnits coarse = ma::length_units(0.2, c);  // outdoor: clouds keep >= 1 voxel per leaf
  EXPECT_GE(c.describe.voxel_size * coarse.feature, 0.2 - 1e-12);
  EXPECT_GE(c.preprocess.voxel_size * coarse.preprocess, 0.2 - 1e-12);
  EXPECT_DOUBLE_EQ(coarse.refine, 0.2);
  ma::AlignConfig scaled;
  scaled.scale.feature_unit = 0.0;  // every length follows the resolution
  EXPECT_DOUBLE_EQ(ma::length_units(0.02, scaled).feature, 0.02);
}

TEST(AlignConfig, TolerancesFollowTheVoxelButNotBelowTheAccuracyUnit) {
  const ma::AlignConfig c;
  EXPECT_DOUBLE_EQ(ma::length_units(0.02, c).tolerance, 0.05);  // RGB-D grid: sensor noise, not the grid
  EXPECT_DOUBLE_EQ(ma::length_units(0.05, c).tolerance, 0.05);
  EXPECT_DOUBLE_EQ(ma::length_units(0.08, c).tolerance, 0.08);
  EXPECT_DOUBLE_EQ(ma::length_units(0.2, c).tolerance, 0.2);
  ma::AlignConfig voxel;
  voxel.scale.accuracy_unit = 0.0;  // tolerances at voxel level at every resolution
  EXPECT_DOUBLE_EQ(ma::length_units(0.02, voxel).tolerance, 0.02);
  EXPECT_DOUBLE_EQ(ma::parse_align_config("scale: {accuracy_unit: 0.02}\n").scale.accuracy_unit, 0.02);
  EXPECT_THROW(ma::parse_align_config("scale: {accuracy_unit: -0.01}\n"), ma::ConfigError);
}

