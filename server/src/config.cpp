#include "mapmerge/server/config.hpp"

#include <cmath>
#include <fstream>
#include <set>
#include <sstream>

#include <yaml-cpp/yaml.h>

namespace mapmerge::server {
namespace {

using align::ConfigError;

/// Throws when `node` has a key not in `known` (or a key that is not a plain name).
void check_keys(const YAML::Node& node, const std::string& section, const std::set<std::string>& known) {
  if (!node.IsMap()) throw ConfigError("config section '" + section + "' must be a map");
  for (const auto& kv : node) {
    if (!kv.first.IsScalar()) throw ConfigError("config section '" + section + "' has a key that is not a name");
    const auto& key = kv.first.Scalar();
    if (known.count(key) == 0) throw ConfigError("unknown config key '" + section + "." + key + "'");
  }
}

template <class T>
void read(const YAML::Node& node, const char* key, T& out, const std::string& section) {
  if (!node[key]) return;
  try {
    out = node[key].as<T>();
  } catch (const YAML::Exception& e) {
    throw ConfigError("bad value for '" + section + "." + key + "': " + e.what());
  }
}

void read_network(const YAML::Node& n, NetworkConfig& c) {
  check_keys(n, "network", {"domain", "profile", "discovery_server", "ros_octomap_pattern", "security_keystore",
                            "security_enclave"});
  read(n, "domain", c.domain, "network");
  read(n, "profile", c.profile, "network");
  read(n, "discovery_server", c.discovery_server, "network");
  read(n, "ros_octomap_pattern", c.ros_octomap_pattern, "network");
  read(n, "security_keystore", c.security_keystore, "network");
  read(n, "security_enclave", c.security_enclave, "network");
}

void read_merge(const YAML::Node& n, MergeConfig& c) {
  check_keys(n, "merge", {"threads", "ingest_threads", "merge_nice", "reference", "global_frame", "global_resolution", "refine_known",
                          "refine_min_change", "search_blocks_fallback",
                          "refine_republish_translation", "refine_republish_rotation_deg", "idle_rescue", "idle_rescue_after_s", "extra_pairs",
                          "extra_min_overlap", "extra_overlap_samples", "extra_global_fallback", "extra_max_jobs",
                          "keep_lost_maps", "alignment_data_hold_s", "session_conflict_hold_s"});
  read(n, "threads", c.threads, "merge");
  read(n, "ingest_threads", c.ingest_threads, "merge");
  read(n, "merge_nice", c.merge_nice, "merge");
  read(n, "reference", c.reference, "merge");
  read(n, "global_frame", c.global_frame, "merge");
  read(n, "global_resolution", c.global_resolution, "merge");
  read(n, "refine_known", c.refine_known, "merge");
  read(n, "refine_min_change", c.refine_min_change, "merge");
  read(n, "search_blocks_fallback", c.search_blocks_fallback, "merge");
  read(n, "refine_republish_translation", c.refine_republish_translation, "merge");
  read(n, "refine_republish_rotation_deg", c.refine_republish_rotation_deg, "merge");
  read(n, "idle_rescue", c.idle_rescue, "merge");
  read(n, "idle_rescue_after_s", c.idle_rescue_after_s, "merge");
  read(n, "extra_pairs", c.extra_pairs, "merge");
  read(n, "extra_min_overlap", c.extra_min_overlap, "merge");
  read(n, "extra_overlap_samples", c.extra_overlap_samples, "merge");
  read(n, "extra_global_fallback", c.extra_global_fallback, "merge");
  read(n, "extra_max_jobs", c.extra_max_jobs, "merge");
  read(n, "keep_lost_maps", c.keep_lost_maps, "merge");
  read(n, "alignment_data_hold_s", c.alignment_data_hold_s, "merge");
  read(n, "session_conflict_hold_s", c.session_conflict_hold_s, "merge");
}

void read_publish(const YAML::Node& n, PublishConfig& c) {
  check_keys(n, "publish",
             {"min_interval_s", "republish_period_s", "status_period_s", "global_encoding", "move_nodes_per_build",
              "move_step_leaves"});
  read(n, "min_interval_s", c.min_interval_s, "publish");
  read(n, "republish_period_s", c.republish_period_s, "publish");
  read(n, "status_period_s", c.status_period_s, "publish");
  read(n, "global_encoding", c.global_encoding, "publish");
  read(n, "move_nodes_per_build", c.move_nodes_per_build, "publish");
  read(n, "move_step_leaves", c.move_step_leaves, "publish");
}

void read_store(const YAML::Node& n, StoreConfig& c) {
  check_keys(n, "store", {"state_dir", "synchronous_full", "retry_period_s"});
  read(n, "state_dir", c.state_dir, "store");
  read(n, "synchronous_full", c.synchronous_full, "store");
  read(n, "retry_period_s", c.retry_period_s, "store");
}

void read_limits(const YAML::Node& n, DecodeLimits& c) {
  check_keys(n, "limits", {"max_bytes", "max_nodes", "max_occupied_voxels", "max_fusion_work", "min_resolution",
                           "max_resolution"});
  read(n, "max_bytes", c.max_bytes, "limits");
  read(n, "max_nodes", c.max_nodes, "limits");
  read(n, "max_occupied_voxels", c.max_occupied_voxels, "limits");
  read(n, "max_fusion_work", c.max_fusion_work, "limits");
  read(n, "min_resolution", c.min_resolution, "limits");
  read(n, "max_resolution", c.max_resolution, "limits");
}

void check(const ServerConfig& c) {
  if (c.network.domain < 0 || c.network.domain > 101) throw ConfigError("network.domain must be in 0..101");
  if (c.merge.threads < 1 || c.merge.threads > 256) throw ConfigError("merge.threads must be in 1..256");
  if (c.merge.ingest_threads < 1 || c.merge.ingest_threads > 256) {
    throw ConfigError("merge.ingest_threads must be in 1..256");
  }
  if (c.merge.merge_nice < 0 || c.merge.merge_nice > 19) throw ConfigError("merge.merge_nice must be in 0..19");
  if (c.merge.global_resolution < 0.0) throw ConfigError("merge.global_resolution must be >= 0");
  if (!(c.merge.refine_min_change >= 0.0 && c.merge.refine_min_change <= 1.0)) {
    throw ConfigError("merge.refine_min_change must be in 0..1");
  }
  if (!(c.merge.extra_min_overlap >= 0.0 && c.merge.extra_min_overlap <= 1.0)) {
    throw ConfigError("merge.extra_min_overlap must be in 0..1");
  }
  if (c.merge.extra_overlap_samples < 1) throw ConfigError("merge.extra_overlap_samples must be >= 1");
  if (c.merge.extra_max_jobs < 0) throw ConfigError("merge.extra_max_jobs must be >= 0");
  if (!(c.merge.session_conflict_hold_s >= 0.0) || !std::isfinite(c.merge.session_conflict_hold_s)) {
    throw ConfigError("merge.session_conflict_hold_s must be a finite number >= 0");
  }
  if (!(c.merge.idle_rescue_after_s >= 0.0) || !std::isfinite(c.merge.idle_rescue_after_s)) {
    throw ConfigError("merge.idle_rescue_after_s must be a finite number >= 0");
  }
  if (!(c.merge.alignment_data_hold_s >= 0.0) || !std::isfinite(c.merge.alignment_data_hold_s)) {
    throw ConfigError("merge.alignment_data_hold_s must be a finite number >= 0");
  }
  if (c.publish.min_interval_s < 0.0 || c.publish.republish_period_s <= 0.0 || c.publish.status_period_s <= 0.0) {
    throw ConfigError("publish periods must be positive");
  }
  if (!(c.store.retry_period_s > 0.0)) throw ConfigError("store.retry_period_s must be positive");
  if (!parse_encoding(c.publish.global_encoding)) throw ConfigError("publish.global_encoding is not an encoding");
  if (!(c.limits.max_fusion_work > 0.0)) throw ConfigError("limits.max_fusion_work must be positive");
  if (c.network.security_enclave.empty()) throw ConfigError("network.security_enclave must not be empty");
  if (c.network.ros_octomap_pattern.find("{robot}") == std::string::npos) {
    throw ConfigError("network.ros_octomap_pattern must contain {robot}");
  }
}

}  // namespace

ServerConfig parse_server_config(const std::string& yaml_text) {
  ServerConfig c;
  YAML::Node root;
  try {
    root = YAML::Load(yaml_text);
  } catch (const YAML::Exception& e) {
    throw ConfigError(std::string("config is not valid YAML: ") + e.what());
  }
  if (root.IsNull()) return c;
  check_keys(root, "(top)", {"network", "merge", "publish", "store", "limits", "align"});
  if (root["network"]) read_network(root["network"], c.network);
  if (root["merge"]) read_merge(root["merge"], c.merge);
  if (root["publish"]) read_publish(root["publish"], c.publish);
  if (root["store"]) read_store(root["store"], c.store);
  if (root["limits"]) read_limits(root["limits"], c.limits);
  if (root["align"]) {
    YAML::Emitter out;
    out << root["align"];
    c.align = align::parse_align_config(out.c_str(), server_align_defaults());
  }
  check(c);
  return c;
}

ServerConfig load_server_config(const std::string& yaml_path) {
  std::ifstream in(yaml_path);
  if (!in) throw ConfigError("cannot read config file '" + yaml_path + "'");
  std::stringstream text;
  text << in.rdbuf();
  return parse_server_config(text.str());
}

}  // namespace mapmerge::server
