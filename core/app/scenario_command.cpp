// `mapmerge scenario`: cut a real map into partial robot maps, each in its own random frame,
// with a chosen overlap between neighbours, and write the ground truth next to them.

#include <cmath>
#include <fstream>
#include <iostream>
#include <random>

#include <nlohmann/json.hpp>

#include "commands.hpp"
#include "mapmerge/map/crop.hpp"
#include "mapmerge/map/map_io.hpp"
#include "scenario.hpp"

namespace mapmerge::app {
namespace {

struct ScenarioOptions {
  std::string map;
  std::string out_dir = "scenario";
  int robots = 3;
  double min_overlap = 0.15;  ///< smallest share of a robot's strip seen by its neighbour [0..1]
  double max_overlap = 0.40;  ///< largest share [0..1]
  double max_tilt_deg = 3.0;  ///< roll/pitch of each robot frame drawn in [-max, max] [deg]
  double max_offset = 10.0;   ///< x/y offset of each robot frame drawn in [-max, max] [m]
  unsigned seed = 1;
};

int run(const ScenarioOptions& o) {
  const auto world = read_octree_file(o.map);
  std::mt19937 rng(o.seed);
  const Scenario scenario = make_scenario(*world, o.robots, o.min_overlap, o.max_overlap, o.max_tilt_deg,
                                          o.max_offset, rng);
  nlohmann::json truth;
  truth["source_map"] = o.map;
  truth["seed"] = o.seed;
  truth["reference"] = scenario.robots.front().id;
  for (const auto& r : scenario.robots) {
    const auto part = crop_and_transform(*world, r.box, r.T_robot_world);
    const std::string file = o.out_dir + "/" + r.id + ".bt";
    write_octree_file(*part, file);
    nlohmann::json j;
    j["id"] = r.id;
    j["map"] = file;
    j["box_min"] = {r.box.min().x(), r.box.min().y(), r.box.min().z()};
    j["box_max"] = {r.box.max().x(), r.box.max().y(), r.box.max().z()};
    j["T_robot_world"] = to_row_major(r.T_robot_world.matrix());
    j["T_global_robot"] = to_row_major(scenario.true_T_global_robot(r).matrix());
    j["overlap_with_previous"] = r.overlap_with_previous;
    j["occupied_leaves"] = part->size();
    truth["robots"].push_back(j);
    std::cout << r.id << ": " << file << "  overlap with previous "
              << std::lround(100.0 * r.overlap_with_previous) << " %\n";
  }
  std::ofstream(o.out_dir + "/truth.json") << truth.dump(2) << "\n";
  return 0;
}

}  // namespace

void add_scenario_command(CLI::App& app, int& exit_code) {
  auto options = std::make_shared<ScenarioOptions>();
  auto* cmd = app.add_subcommand("scenario", "cut a real map into partial robot maps with known transforms");
  cmd->add_option("map", options->map, "the whole map (.bt or .ot)")->required()->check(CLI::ExistingFile);
  cmd->add_option("-o,--out-dir", options->out_dir, "where to write <robot>.bt and truth.json")
      ->check(CLI::ExistingDirectory);
  cmd->add_option("-n,--robots", options->robots, "number of robots")->check(CLI::Range(2, 16));
  cmd->add_option("--min-overlap", options->min_overlap, "smallest overlap between neighbours")->check(CLI::Range(0.0, 0.9));
  cmd->add_option("--max-overlap", options->max_overlap, "largest overlap between neighbours")->check(CLI::Range(0.0, 0.9));
  cmd->add_option("--max-tilt", options->max_tilt_deg, "largest roll/pitch of a robot frame [deg]");
  cmd->add_option("--max-offset", options->max_offset, "largest x/y offset of a robot frame [m]");
  cmd->add_option("--seed", options->seed, "random seed");
  cmd->callback([options, &exit_code] { exit_code = run(*options); });
}

}  // namespace mapmerge::app
