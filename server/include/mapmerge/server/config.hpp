#pragma once
/// Settings of mapmerge-server: plain structs, filled from YAML and then from the command line.

#include <string>

#include "mapmerge/align/config.hpp"
#include "mapmerge/map/map_codec.hpp"

namespace mapmerge::server {

/// How the server talks DDS (read by DdsIo).
struct NetworkConfig {
  int domain = 0;                    ///< DDS domain id (0..101)
  std::string profile = "local";     ///< "local", "default" or a Fast DDS XML file
  std::string discovery_server;      ///< "HOST:PORT" of a Fast DDS discovery server; empty: none
  std::string ros_octomap_pattern = "rt/{robot}/octomap_binary";  ///< ROS 2 map topics, "{robot}" = id
  std::string security_keystore;     ///< DDS Security keystore (scripts/make-keystore); empty: ROS 2's
                                     ///< ROS_SECURITY_* environment, else security off
  std::string security_enclave = "mapmerge_server";  ///< the server's enclave in the keystore
};

/// The merge policy (read by Pipeline and Scheduler).
struct MergeConfig {
  int threads = 2;                   ///< threads running merges: global searches, refinements, extra pairs [count]
  int ingest_threads = 1;            ///< threads checking and storing received maps [count]: a map never
                                     ///< waits behind a merge
  int merge_nice = 10;               ///< the merge threads run this many nice levels below the server's
                                     ///< priority, so a received map's check and fusion go first (0: same)
  std::string reference;             ///< robot defining the global frame; empty: the first heard
  std::string global_frame = "global";  ///< frame id of the global map and poses
  double global_resolution = 0.0;    ///< voxel edge of the global map [m]; 0: the reference's
  bool refine_known = true;          ///< refine a known robot's transform when its map changes
  double refine_min_change = 0.1;    ///< ... once its map or its partner's has changed by this share of
                                     ///< its nodes since the pair was last aligned (a map that barely
                                     ///< changed keeps its transform; 0: on every change) [0..1]
  bool search_blocks_fallback = true;  ///< a whole-map global search that accepts nothing is run once
                                       ///< more block by block (the paper's *_DIV: a small overlap is a
                                       ///< larger share of one block); ignored when align.submodels is on
  double refine_republish_translation = 0.02;  ///< a refinement moving a robot more than this republishes [m]
  double refine_republish_rotation_deg = 0.1;  ///< ... or turning it more than this [deg]
  bool idle_rescue = true;           ///< on spare threads, a robot still unknown gets the rescue's search
                                     ///< (align.rescue: denser features, ~3x a search) against each
                                     ///< partner whose search refused it for no ambiguity, once per pair
                                     ///< of maps (moot when align.rescue.enabled: every search has it)
  double idle_rescue_after_s = 10.0; ///< ... once that refusal (both maps as they are now) is this old: a
                                     ///< robot whose map still grows gets new searches instead [s]
  bool extra_pairs = true;           ///< on spare threads, align aligned robots that share no edge yet but
                                     ///< overlap (by their pose estimates), so the pose graph gets cycles
  double extra_min_overlap = 0.1;    ///< estimated share of the smaller map's occupied voxels on the
                                     ///< other's for an extra pair [0..1]
  int extra_overlap_samples = 1000;  ///< occupied voxels sampled by the overlap estimate [count]
  bool extra_global_fallback = true;  ///< an extra pair whose local refinement (from the pose estimates)
                                      ///< fails gets a global search
  int extra_max_jobs = 0;            ///< extra pairs aligned at once [count]; 0: threads - 1 (at least 1),
                                     ///< so a merge thread is free for searches and refinements
  bool keep_lost_maps = true;        ///< a robot whose writers are gone (left, or lease expired) stays
                                     ///< fused in the global map (false: left out until it returns)
  double alignment_data_hold_s = 30.0;  ///< a robot's prepared map (alignment clouds, kd-trees, free
                                        ///< space), built for a search or refinement, is let go of when
                                        ///< no alignment used it for this long, and built again from the
                                        ///< map's bytes when one needs it [s]
  double session_conflict_hold_s = 30.0;  ///< a session of a robot that a newer session replaced is refused
                                          ///< while the newer one published within this time: two
                                          ///< participants use one robot id [s]
};

/// When the global map and poses go out (read by the server's main loop).
struct PublishConfig {
  double min_interval_s = 0.2;       ///< at most one global map per this period [s]
  double republish_period_s = 2.0;   ///< republish map and poses this often for late joiners [s]
  double status_period_s = 1.0;      ///< server status this often [s]
  std::string global_encoding = "octomap-bt";  ///< encoding of the native global map
  std::size_t move_nodes_per_build = 250000;   ///< robots to fuse whole (a new robot, a moved pose) per
                                               ///< global-map build, by their maps' nodes (~0.3 s of
                                               ///< fusion on 2 cores), at least one; the others keep
                                               ///< their fused pose until the next builds, so updates
                                               ///< are published in between [count; 0: all at once]
  std::size_t move_step_leaves = 50000;        ///< a robot moved to a new pose (its map unchanged)
                                               ///< moves this many of its leaves a build (~60 ms of
                                               ///< fusion on 2 cores), so the updates of the others
                                               ///< are not held back by a large map's move; each
                                               ///< build's map is whole, part of the robot at its
                                               ///< old pose [count; 0: a move in one build]
};

/// Where and how the registry persists (read by Store).
struct StoreConfig {
  std::string state_dir;             ///< directory of state.sqlite; empty: no persistence
  bool synchronous_full = true;      ///< SQLite synchronous=FULL (else NORMAL: safe for crashes, not power loss)
  double retry_period_s = 2.0;       ///< while writes failed (disk full, read-only), retry them this often [s]
};

/// core/align's defaults with the rescue off (ServerConfig::align).
inline align::AlignConfig server_align_defaults() {
  align::AlignConfig c;
  c.rescue.enabled = false;
  return c;
}

struct ServerConfig {
  NetworkConfig network;
  MergeConfig merge;
  PublishConfig publish;
  StoreConfig store;
  DecodeLimits limits;               ///< bounds every incoming map must respect
  /// The registration pipeline (core/align), with its defaults but for `rescue.enabled`, off
  /// unless the file sets it: a failed global search with the rescue costs ~4x one without, and
  /// the server retries a robot's search as its map grows and falls back to blocks
  /// (merge.search_blocks_fallback) instead. `mapmerge merge`, which has one chance, keeps it.
  align::AlignConfig align = server_align_defaults();
};

/// Reads a YAML file with sections `network`, `merge`, `publish`, `store`, `limits` and
/// `align` (core/align's format). Missing keys keep defaults; unknown keys throw
/// align::ConfigError.
ServerConfig load_server_config(const std::string& yaml_path);
ServerConfig parse_server_config(const std::string& yaml_text);

}  // namespace mapmerge::server
