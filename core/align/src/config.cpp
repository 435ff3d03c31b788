#include <algorithm>
#include <cmath>
#include <fstream>
#include <map>
#include <set>
#include <sstream>

#include <nlohmann/json.hpp>
#include <yaml-cpp/yaml.h>

#include "mapmerge/align/config.hpp"

namespace mapmerge::align {
namespace {

/// Calls f(section, key, field&) for every setting: the one list that load and dump share.
template <class Config, class F>
void for_each_field(Config& c, F&& f) {
  f("", "seed", c.seed);
  f("scale", "feature_unit", c.scale.feature_unit);
  f("scale", "accuracy_unit", c.scale.accuracy_unit);
  f("points", "min_occupancy", c.points.min_occupancy);
  f("points", "max_points", c.points.max_points);
  auto& p = c.preprocess;
  f("preprocess", "pass_through", p.pass_through);
  f("preprocess", "z_min", p.z_min);
  f("preprocess", "z_max", p.z_max);
  f("preprocess", "remove_ground", p.remove_ground);
  f("preprocess", "ground_distance", p.ground_distance);
  f("preprocess", "ground_max_tilt_deg", p.ground_max_tilt_deg);
  f("preprocess", "voxel_size", p.voxel_size);
  f("preprocess", "outlier_removal", p.outlier_removal);
  f("preprocess", "outlier_mean_k", p.outlier_mean_k);
  f("preprocess", "outlier_stddev", p.outlier_stddev);
  f("preprocess", "normal_radius", p.normal_radius);
  f("preprocess", "fine_normal_radius", p.fine_normal_radius);
  f("preprocess", "orient_normals_to_free", p.orient_normals_to_free);
  auto& s = c.submodels;
  f("submodels", "enabled", s.enabled);
  f("submodels", "block_size", s.block_size);
  f("submodels", "grid_3d", s.grid_3d);
  f("submodels", "block_height", s.block_height);
  f("submodels", "block_overlap", s.block_overlap);
  f("submodels", "min_keypoints", s.min_keypoints);
  f("submodels", "early_stop", s.early_stop);
  f("submodels", "early_stop_inlier_share", s.early_stop_inlier_share);
  f("submodels", "threads", s.threads);
  auto& k = c.keypoints;
  f("keypoints", "salient_radius", k.salient_radius);
  f("keypoints", "non_max_radius", k.non_max_radius);
  f("keypoints", "gamma_21", k.gamma_21);
  f("keypoints", "gamma_32", k.gamma_32);
  f("keypoints", "min_neighbors", k.min_neighbors);
  f("keypoints", "threads", k.threads);
  f("describe", "voxel_size", c.describe.voxel_size);
  f("describe", "normal_radius", c.describe.normal_radius);
  f("describe", "method", c.describe.method);
  f("describe", "radius", c.describe.radius);
  f("describe", "threads", c.describe.threads);
  auto& m = c.match;
  f("match", "method", m.method);
  f("match", "k_nearest", m.k_nearest);
  f("match", "mutual", m.mutual);
  f("match", "max_correspondences", m.max_correspondences);
  f("match", "iterations", m.iterations);
  f("match", "seed_pairs", m.seed_pairs);
  f("match", "edge_similarity", m.edge_similarity);
  f("match", "min_edge", m.min_edge);
  f("match", "inlier_distance", m.inlier_distance);
  f("match", "min_consensus", m.min_consensus);
  f("match", "max_hypotheses", m.max_hypotheses);
  f("match", "gc_size", m.gc_size);
  f("match", "gc_threshold", m.gc_threshold);
  auto& v = c.validate;
  f("validate", "d_th", v.d_th);
  f("validate", "max_pair_distance", v.max_pair_distance);
  f("validate", "n_th", v.n_th);
  f("validate", "min_inlier_fraction", v.min_inlier_fraction);
  f("validate", "max_fitness", v.max_fitness);
  f("validate", "conflict_distance", v.conflict_distance);
  f("validate", "min_inlier_share", v.min_inlier_share);
  f("validate", "max_near_conflict_share", v.max_near_conflict_share);
  f("validate", "conflict_weight", v.conflict_weight);
  f("validate", "max_tilt_deg", v.max_tilt_deg);
  f("validate", "ambiguity_ratio", v.ambiguity_ratio);
  f("validate", "distinct_rotation_deg", v.distinct_rotation_deg);
  f("validate", "distinct_translation", v.distinct_translation);
  f("validate", "coarse_points", v.coarse_points);
  f("validate", "refine_candidates", v.refine_candidates);
  f("validate", "refine_score_ratio", v.refine_score_ratio);
  auto& r = c.refine;
  f("refine", "method", r.method);
  f("refine", "point_to_plane", r.point_to_plane);
  f("refine", "max_iterations", r.max_iterations);
  f("refine", "final_iterations", r.final_iterations);
  f("refine", "max_correspondence", r.max_correspondence);
  f("refine", "final_correspondence", r.final_correspondence);
  f("refine", "crop_margin", r.crop_margin);
  f("refine", "convergence_translation", r.convergence_translation);
  f("refine", "convergence_rotation_deg", r.convergence_rotation_deg);
  f("refine", "max_points", r.max_points);
  f("refine", "final_points", r.final_points);
  f("refine", "restart_deg", r.restart_deg);
  f("refine", "restart_fitness", r.restart_fitness);
  f("refine", "ndt_resolution", r.ndt_resolution);
  f("refine", "ndt_step", r.ndt_step);
  auto& q = c.rescue;
  f("rescue", "enabled", q.enabled);
  f("rescue", "describe_voxel_size", q.describe_voxel_size);
  f("rescue", "non_max_radius", q.non_max_radius);
}

template <class E>
const std::map<std::string, E>& enum_names();
template <>
const std::map<std::string, Descriptor>& enum_names() {
  static const std::map<std::string, Descriptor> m{{"fpfh", Descriptor::kFpfh},
                                                   {"shot", Descriptor::kShot}};
  return m;
}
template <>
const std::map<std::string, MatchMethod>& enum_names() {
  static const std::map<std::string, MatchMethod> m{{"ransac", MatchMethod::kRansac},
                                                    {"sac_ia", MatchMethod::kSacIa},
                                                    {"prerejective", MatchMethod::kPrerejective},
                                                    {"gcc", MatchMethod::kGcc}};
  return m;
}
template <>
const std::map<std::string, RefineMethod>& enum_names() {
  static const std::map<std::string, RefineMethod> m{{"icp", RefineMethod::kIcp},
                                                     {"oicp", RefineMethod::kOicp},
                                                     {"ndt", RefineMethod::kNdt},
                                                     {"none", RefineMethod::kNone}};
  return m;
}

template <class E>
std::string enum_to_string(E e) {
  for (const auto& [name, value] : enum_names<E>())
    if (value == e) return name;
  return "?";
}

std::string full_key(const char* section, const char* key) {
  return *section ? std::string(section) + "." + key : std::string(key);
}

template <class T>
void read_value(const YAML::Node& node, const std::string& name, T& out) {
  if constexpr (std::is_enum_v<T>) {
    const auto text = node.IsScalar() ? node.as<std::string>() : std::string("(not a scalar)");
    const auto& names = enum_names<T>();
    const auto it = names.find(text);
    if (it == names.end()) {
      std::string allowed;
      for (const auto& kv : names) allowed += (allowed.empty() ? "" : ", ") + kv.first;
      throw ConfigError("config key '" + name + "': '" + text + "' is not one of " + allowed);
    }
    out = it->second;
  } else {
    try {
      out = node.as<T>();
    } catch (const YAML::Exception&) {
      throw ConfigError("config key '" + name + "': cannot read '" +
                        (node.IsScalar() ? node.Scalar() : std::string("(not a scalar)")) +
                        "' as " + (std::is_same_v<T, bool> ? "a boolean" : "a number"));
    }
  }
}

/// A mapping key as a name; throws for keys that are sequences or mappings (`? [a, b]: 1`).
std::string key_name(const YAML::Node& key, const std::string& section) {
  if (!key.IsScalar()) {
    throw ConfigError("config " + (section.empty() ? std::string("document") : "section '" + section + "'") +
                      " has a key that is not a name");
  }
  return key.Scalar();
}

/// Rejects keys of the document that no field has.
void check_known_keys(const YAML::Node& root) {
  std::set<std::string> known, sections;
  AlignConfig probe;
  for_each_field(probe, [&](const char* section, const char* key, auto&) {
    known.insert(full_key(section, key));
    if (*section) sections.insert(section);
  });
  for (const auto& kv : root) {
    const auto top = key_name(kv.first, "");
    if (sections.count(top)) {
      if (!kv.second.IsMap() && !kv.second.IsNull())
        throw ConfigError("config section '" + top + "' must be a mapping");
      for (const auto& inner : kv.second) {
        const auto name = top + "." + key_name(inner.first, top);
        if (!known.count(name)) throw ConfigError("unknown config key '" + name + "'");
      }
    } else if (!known.count(top)) {
      throw ConfigError("unknown config key '" + top + "'");
    }
  }
}

void require(bool ok, const std::string& what) {
  if (!ok) throw ConfigError("bad config value: " + what);
}

}  // namespace

LengthUnits length_units(double res, const AlignConfig& c) {
  const double u = c.scale.feature_unit > 0.0 ? c.scale.feature_unit : res;
  LengthUnits units;
  units.res = res;
  units.tolerance = std::max(res, c.scale.accuracy_unit);
  units.preprocess = std::max(u, res / c.preprocess.voxel_size);  // ICP cloud leaf >= 1 voxel
  units.feature = std::max(u, res / c.describe.voxel_size);       // describe leaf >= 1 voxel
  units.refine = std::max(units.feature, res);
  return units;
}

const char* to_string(Descriptor d) { return d == Descriptor::kFpfh ? "fpfh" : "shot"; }
const char* to_string(MatchMethod m) {
  switch (m) {
    case MatchMethod::kRansac: return "ransac";
    case MatchMethod::kSacIa: return "sac_ia";
    case MatchMethod::kPrerejective: return "prerejective";
    case MatchMethod::kGcc: return "gcc";
  }
  return "?";
}
const char* to_string(RefineMethod m) {
  switch (m) {
    case RefineMethod::kIcp: return "icp";
    case RefineMethod::kOicp: return "oicp";
    case RefineMethod::kNdt: return "ndt";
    case RefineMethod::kNone: return "none";
  }
  return "?";
}

void check_align_config(const AlignConfig& c) {
  require(c.scale.feature_unit >= 0.0, "scale.feature_unit >= 0");
  require(c.scale.accuracy_unit >= 0.0, "scale.accuracy_unit >= 0");
  require(c.preprocess.voxel_size > 0.0, "preprocess.voxel_size > 0");
  require(c.preprocess.normal_radius > 0.0, "preprocess.normal_radius > 0");
  require(c.preprocess.fine_normal_radius > 0.0, "preprocess.fine_normal_radius > 0");
  require(c.preprocess.outlier_mean_k >= 1, "preprocess.outlier_mean_k >= 1");
  require(c.preprocess.z_min <= c.preprocess.z_max, "preprocess.z_min <= z_max");
  require(c.submodels.block_size > 0.0 && c.submodels.block_height > 0.0,
          "submodels.block_size/block_height > 0");
  require(c.submodels.block_overlap >= 0.0 && c.submodels.block_overlap < 0.95,
          "submodels.block_overlap in [0, 0.95)");
  require(c.keypoints.salient_radius > 0.0 && c.keypoints.non_max_radius > 0.0,
          "keypoints radii > 0");
  require(c.describe.radius > 0.0, "describe.radius > 0");
  require(c.describe.voxel_size > 0.0 && c.describe.normal_radius > 0.0,
          "describe.voxel_size > 0 and describe.normal_radius > 0");
  require(c.match.k_nearest >= 1, "match.k_nearest >= 1");
  require(c.match.iterations >= 1, "match.iterations >= 1");
  require(c.match.edge_similarity >= 0.0 && c.match.edge_similarity < 1.0,
          "match.edge_similarity in [0, 1)");
  require(c.match.min_consensus >= 3, "match.min_consensus >= 3");
  require(c.match.max_hypotheses >= 1, "match.max_hypotheses >= 1");
  require(c.validate.d_th > 0.0, "validate.d_th > 0");
  require(c.validate.max_pair_distance >= 0.0, "validate.max_pair_distance >= 0");
  require(c.validate.min_inlier_share >= 0.0 && c.validate.min_inlier_share <= 1.0,
          "validate.min_inlier_share in [0, 1]");
  require(c.validate.max_near_conflict_share >= 0.0 && c.validate.max_near_conflict_share <= 1.0,
          "validate.max_near_conflict_share in [0, 1]");
  require(c.validate.max_tilt_deg >= 0.0 && c.validate.max_tilt_deg <= 180.0, "validate.max_tilt_deg in [0, 180]");
  require(c.validate.coarse_points >= 10, "validate.coarse_points >= 10");
  require(c.validate.refine_candidates >= 1, "validate.refine_candidates >= 1");
  require(c.refine.max_iterations >= 1, "refine.max_iterations >= 1");
  require(c.refine.final_iterations >= 1, "refine.final_iterations >= 1");
  require(c.refine.max_correspondence > 0.0 && c.refine.final_correspondence > 0.0,
          "refine correspondence distances > 0");
  require(c.refine.max_points >= 10, "refine.max_points >= 10");
  require(c.refine.restart_deg >= 0.0 && c.refine.restart_deg <= 45.0, "refine.restart_deg in [0, 45]");
  require(c.refine.restart_fitness >= 0.0, "refine.restart_fitness >= 0");
  require(c.rescue.describe_voxel_size > 0.0 && c.rescue.non_max_radius > 0.0,
          "rescue.describe_voxel_size > 0 and rescue.non_max_radius > 0");
}

AlignConfig parse_align_config(const std::string& yaml_text, const AlignConfig& base) {
  YAML::Node root;
  try {
    root = YAML::Load(yaml_text);
  } catch (const YAML::Exception& e) {
    throw ConfigError(std::string("config is not valid YAML: ") + e.what());
  }
  AlignConfig config = base;
  if (root.IsNull()) return config;
  if (!root.IsMap()) throw ConfigError("config must be a YAML mapping of sections");
  check_known_keys(root);
  for_each_field(config, [&](const char* section, const char* key, auto& field) {
    const YAML::Node node = *section ? root[section][key] : root[key];
    if (node) read_value(node, full_key(section, key), field);
  });
  check_align_config(config);
  return config;
}

AlignConfig load_align_config(const std::string& yaml_path) {
  std::ifstream in(yaml_path);
  if (!in) throw ConfigError("cannot open config file '" + yaml_path + "'");
  std::stringstream text;
  text << in.rdbuf();
  try {
    return parse_align_config(text.str());
  } catch (const ConfigError& e) {
    throw ConfigError("'" + yaml_path + "': " + e.what());
  }
}

std::string dump_align_config_yaml(const AlignConfig& config) {
  std::map<std::string, std::vector<std::pair<std::string, std::string>>> sections;
  std::vector<std::pair<std::string, std::string>> top;
  AlignConfig copy = config;
  for_each_field(copy, [&](const char* section, const char* key, auto& field) {
    using T = std::decay_t<decltype(field)>;
    std::ostringstream value;
    if constexpr (std::is_enum_v<T>) {
      value << enum_to_string(field);
    } else if constexpr (std::is_same_v<T, bool>) {
      value << (field ? "true" : "false");
    } else if constexpr (std::is_floating_point_v<T>) {
      if (std::isinf(field)) value << (field > 0 ? ".inf" : "-.inf");
      else value << field;
    } else {
      value << field;
    }
    (*section ? sections[section] : top).emplace_back(key, value.str());
  });
  std::ostringstream out;
  for (const auto& [k, v] : top) out << k << ": " << v << "\n";
  for (const auto& [name, fields] : sections) {
    out << name << ":\n";
    for (const auto& [k, v] : fields) out << "  " << k << ": " << v << "\n";
  }
  return out.str();
}

std::string dump_align_config_json(const AlignConfig& config) {
  nlohmann::json j = nlohmann::json::object();
  AlignConfig copy = config;
  for_each_field(copy, [&](const char* section, const char* key, auto& field) {
    using T = std::decay_t<decltype(field)>;
    nlohmann::json& slot = *section ? j[section][key] : j[key];
    if constexpr (std::is_enum_v<T>) slot = enum_to_string(field);
    else if constexpr (std::is_floating_point_v<T>) slot = std::isfinite(field) ? nlohmann::json(field) : nlohmann::json(nullptr);
    else slot = field;
  });
  return j.dump();
}

}  // namespace mapmerge::align
