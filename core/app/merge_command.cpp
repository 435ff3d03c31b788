// `mapmerge merge TARGET SOURCE [-o merged.bt] [--config file.yaml] [--json]` (issue 3):
// aligns SOURCE to TARGET, prints the result, optionally writes the fused map.
#include <chrono>
#include <cstdio>
#include <future>
#include <iomanip>
#include <iostream>
#include <memory>
#include <sstream>
#include <vector>

#include <fcntl.h>
#include <sys/resource.h>
#include <unistd.h>

#include <nlohmann/json.hpp>

#include "commands.hpp"
#include "mapmerge/align/align.hpp"
#include "mapmerge/map/fusion.hpp"
#include "mapmerge/map/global_fusion.hpp"
#include "mapmerge/map/held_map.hpp"
#include "mapmerge/map/map_io.hpp"

namespace mapmerge::app {
namespace {

/// Silences stderr (file descriptor 2) while alive: Debian's liboctomap reports every file it
/// reads or writes there ("Reading binary octree...", "Writing N nodes").
class QuietStderr {
 public:
  QuietStderr() {
    std::fflush(stderr);
    std::cerr.flush();
    saved_ = ::dup(2);
    const int null = ::open("/dev/null", O_WRONLY);
    if (saved_ >= 0 && null >= 0) ::dup2(null, 2);
    if (null >= 0) ::close(null);
  }
  ~QuietStderr() {
    std::fflush(stderr);
    std::cerr.flush();
    if (saved_ >= 0) {
      ::dup2(saved_, 2);
      ::close(saved_);
    }
  }
  QuietStderr(const QuietStderr&) = delete;
  QuietStderr& operator=(const QuietStderr&) = delete;

 private:
  int saved_ = -1;
};

/// The process ends after the command: trees of up to millions of nodes are left to the OS
/// instead of being freed node by node (tens of milliseconds). They stay reachable from a
/// static pointer, so leak checkers do not report them.
void keep_until_exit(std::shared_ptr<const void> map) {
  static auto* kept = new std::vector<std::shared_ptr<const void>>();
  kept->push_back(std::move(map));
}

struct MergeOptions {
  std::string target, source, output, config;
  bool json = false;
};

std::string json_result(const align::AlignResult& r, double seconds) {
  nlohmann::json j;
  j["accepted"] = r.accepted;
  std::vector<double> T;
  for (int i = 0; i < 4; ++i)
    for (int k = 0; k < 4; ++k) T.push_back(r.T_target_source(i, k));
  j["T_target_source"] = T;
  j["fitness"] = std::isfinite(r.fitness) ? nlohmann::json(r.fitness) : nlohmann::json(nullptr);
  j["inliers"] = r.inliers;
  j["overlap"] = r.overlap;
  j["inlier_share"] = r.inlier_share;
  j["submodel"] = r.submodel;
  j["hypotheses"] = r.hypotheses;
  j["rescued"] = r.rescued;
  j["reason"] = r.reason;
  j["time_s"] = seconds;
  j["stages"] = nlohmann::json::parse(align::timings_json(r.timings));
  return j.dump();
}

void print_text(const align::AlignResult& r, double seconds) {
  std::cout << (r.accepted ? "accepted" : "not accepted: " + r.reason) << "\n";
  std::cout << std::fixed << std::setprecision(6) << "T_target_source =\n"
            << r.T_target_source << "\n"
            << "fitness " << r.fitness << " m, inliers " << r.inliers << ", overlap "
            << std::setprecision(3) << r.overlap << ", inlier share " << r.inlier_share
            << ", time " << seconds << " s\n";
}

int run_merge(const MergeOptions& o) {
  const auto t0 = std::chrono::steady_clock::now();
  align::AlignConfig config;
  try {
    if (!o.config.empty()) config = align::load_align_config(o.config);
  } catch (const align::ConfigError& e) {
    std::cerr << "mapmerge merge: " << e.what() << "\n";
    return 2;
  }
  // Each map is read, checked and prepared for the alignment on a thread of its own, so the
  // smaller map's preparation starts as soon as it is read. Fused as the server fuses
  // (GlobalFusion, the sum of both maps' log-odds clamped once, on the target's grid), off the
  // maps' bytes: no octree is built to write a `.bt` file. The target needs no transform: it is
  // placed on a third thread of the lowest priority from the moment it is read (the alignment
  // leaves part of the two cores idle, ~0.6 of one on the paper's pair), and the source is staged
  // after it (GlobalFusion::stage).
  std::shared_ptr<const HeldMap> target, source;
  std::promise<std::shared_ptr<const HeldMap>> source_read;  // for the fusion's thread
  std::shared_future<std::shared_ptr<const HeldMap>> source_ready = source_read.get_future().share();
  std::shared_ptr<GlobalFusion> fused;
  std::future<GlobalFuseResult> target_placed;
  unsigned fusion_threads = 1;
  align::AlignResult result;
  try {
    QuietStderr quiet;  // (OctoMap may report a file it reads)
    std::future<align::PreparedMap> source_side = std::async(std::launch::async, [&] {
      try {
        source = read_map_file(o.source);
      } catch (...) {
        source_read.set_exception(std::current_exception());
        throw;
      }
      source_read.set_value(source);
      return align::prepare_map(*source, config);
    });
    target = read_map_file(o.target);
    if (!o.output.empty()) {
      fused = std::make_shared<GlobalFusion>(target->resolution(), FuseConfig{});
      keep_until_exit(fused);
      fusion_threads = fused->threads();
      fused->set_threads(1);
      target_placed = std::async(std::launch::async, [&] {
        // Background work: its result is needed only once the alignment is done, so it takes the
        // cores only when the two preparations and the search leave one idle (Linux: a thread's
        // own nice value). On the paper's pair the target's preparation, no longer sharing its
        // core, ends ~30 ms sooner (merge -o median 0.485 -> 0.457 s, 12 interleaved runs;
        // bench/results/README.md, session 24).
        ::setpriority(PRIO_PROCESS, static_cast<id_t>(::gettid()), 19);
        GlobalFuseResult placed = fused->set("target", target, Eigen::Matrix4d::Identity());
        fused->stage(source_ready.get());  // (a source that could not be read ends here)
        return placed;
      });
    }
    const auto t_prepare = std::chrono::steady_clock::now();  // stages.total_ms: preparation + alignment
    const align::PreparedMap target_prepared = align::prepare_map(*target, config);
    const align::PreparedMap source_prepared = source_side.get();
    result = align::align(target_prepared, source_prepared, config);
    result.timings.total_ms =
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t_prepare).count();
  } catch (const MapError& e) {
    std::cerr << "mapmerge merge: " << e.what() << "\n";
    return 1;  // (the threads still running are waited for by their futures)
  } catch (const std::invalid_argument& e) {
    std::cerr << "mapmerge merge: " << e.what() << "\n";
    return 1;
  }
  if (result.accepted && !o.output.empty()) {
    GlobalFuseResult r = target_placed.get();
    fused->set_threads(fusion_threads);
    if (r.ok) r = fused->set("source", source, result.T_target_source);
    if (!r.ok) {
      std::cerr << "mapmerge merge: fusion failed: " << r.reason << "\n";
      return 1;
    }
    try {
      QuietStderr quiet;
      if (is_ot_path(o.output)) {
        const std::shared_ptr<const octomap::OcTree> tree = fused->tree();
        keep_until_exit(tree);
        write_octree_file(*tree, o.output);
      } else {
        write_bt_file(fused->encode().bt, o.output);
      }
    } catch (const MapError& e) {
      std::cerr << "mapmerge merge: " << e.what() << "\n";
      return 1;
    }
  }
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  if (o.json) std::cout << json_result(result, seconds) << "\n";
  else print_text(result, seconds);
  if (!result.accepted && !o.output.empty() && !o.json)
    std::cerr << "mapmerge merge: not accepted, " << o.output << " not written\n";
  keep_until_exit(std::move(target));
  keep_until_exit(std::move(source));
  return result.accepted ? 0 : 3;
}

}  // namespace

void add_merge_command(CLI::App& app, int& exit_code) {
  auto opts = std::make_shared<MergeOptions>();
  auto* cmd = app.add_subcommand(
      "merge", "Align SOURCE to TARGET (global search) and optionally write the fused map.\n"
               "Exit codes: 0 accepted, 3 no hypothesis accepted, 1 bad input, 2 bad usage.");
  cmd->add_option("TARGET", opts->target, "target map (.bt or .ot): defines the frame")->required();
  cmd->add_option("SOURCE", opts->source, "source map (.bt or .ot): merged into TARGET's frame")->required();
  cmd->add_option("-o,--output", opts->output, "write the fused map here (.bt, or .ot for log-odds)");
  cmd->add_option("--config", opts->config, "YAML file with pipeline settings (see docs)");
  cmd->add_flag("--json", opts->json, "print one JSON object on stdout");
  cmd->callback([opts, &exit_code] { exit_code = run_merge(*opts); });
}

}  // namespace mapmerge::app
