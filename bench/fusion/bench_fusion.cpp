// Global fusion of N robots' maps cut from one real map (strips along x, each in its own turned
// frame, as bench/server cuts them): the full re-fusion the server used to run on every change
// against GlobalFusion's incremental update of one robot (its map grown, same pose), a pose
// change, and the outputs (encode, provenance). Wall time (GlobalFusion uses several threads:
// run it on an idle machine). Memory: the global sums and a robot's decoded map against its payload.
#include <chrono>
#include <algorithm>
#include <cstdio>
#include <ctime>
#include <random>

#include <CLI/CLI.hpp>
#include <Eigen/Geometry>

#include "mapmerge/map/crop.hpp"
#include "mapmerge/map/fusion.hpp"
#include "mapmerge/map/global_fusion.hpp"
#include "mapmerge/map/map_codec.hpp"
#include "mapmerge/map/map_io.hpp"

using namespace mapmerge;

namespace {

/// Wall time [ms]: GlobalFusion may work on several threads (run on an idle machine).
double wall_ms() {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

double median(std::vector<double> v) {
  std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(v.size() / 2), v.end());
  return v[v.size() / 2];
}

struct Robot {
  std::shared_ptr<const octomap::OcTree> map, grown;  ///< as the server holds them: decoded from `.bt`
  std::shared_ptr<const std::vector<std::uint8_t>> map_body, grown_body;  ///< their binary bodies
  Eigen::Matrix4d T_global_robot;
  std::size_t payload_bytes = 0;
};

/// N strips of `share` of the map's length; robot i's grown map reaches `grow` m further.
/// Robots other than the first are turned by a random yaw and a roll and pitch of up to `tilt`.
std::vector<Robot> make_fleet(const octomap::OcTree& world, int n, double share, double grow, double tilt) {
  double x0, y0, z0, x1, y1, z1;
  world.getMetricMin(x0, y0, z0);
  world.getMetricMax(x1, y1, z1);
  const double length = std::max((x1 - x0) * share, 2.0 * (x1 - x0) / (n + 1));
  const double step = n > 1 ? ((x1 - x0) - length) / (n - 1) : 0.0;
  std::mt19937 rng(1234 + static_cast<unsigned>(n));
  std::uniform_real_distribution<double> yaw(-M_PI, M_PI), off(-5, 5), tilted(-tilt, tilt);
  std::vector<Robot> fleet;
  for (int i = 0; i < n; ++i) {
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    if (i != 0) {  // drawn in the order GCC drew them before --tilt, so --tilt 0 keeps the fleets
      const double a = yaw(rng);
      const double y = off(rng);
      const double x = off(rng);
      const double roll = tilt > 0 ? tilted(rng) : 0.0;
      const double pitch = tilt > 0 ? tilted(rng) : 0.0;
      T = make_transform(x, y, 0, roll, pitch, a);
    }
    auto box = [&](double extra) {
      return Eigen::AlignedBox3d(Eigen::Vector3d(x0 + i * step, y0, z0), Eigen::Vector3d(x0 + i * step + length + extra, y1, z1));
    };
    Robot r;
    auto received = [](const octomap::OcTree& tree, std::shared_ptr<const std::vector<std::uint8_t>>& body) {
      DecodeResult d = decode_map(encode_map(tree, Encoding::kOctomapBt), Encoding::kOctomapBt, DecodeLimits{});
      body = d.binary_body;
      return std::shared_ptr<const octomap::OcTree>(std::move(d.tree));
    };
    r.map = received(*crop_and_transform(world, box(0), T), r.map_body);
    r.grown = received(*crop_and_transform(world, box(grow), T), r.grown_body);
    r.T_global_robot = T.inverse().matrix();
    r.payload_bytes = encode_map(*r.map, Encoding::kOctomapBt).size();
    fleet.push_back(std::move(r));
  }
  return fleet;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"global fusion bench: full re-fusion vs incremental update (wall time)"};
  std::string map = "fr_079.bt";
  std::vector<int> sizes{2, 4, 8, 16};
  double share = 0.45, grow = 1.0;
  app.add_option("--map", map, "map in data/");
  app.add_option("--robots", sizes, "fleet sizes")->delimiter(',');
  app.add_option("--strip-share", share, "share of the map's length each robot sees");
  app.add_option("--grow", grow, "how far a robot's map grows in one update [m]");
  double tilt_deg = 0.0;
  app.add_option("--tilt", tilt_deg, "largest roll and pitch of a robot's frame [deg]")->check(CLI::Range(0.0, 45.0));
  int repeat = 1;
  app.add_option("--repeat", repeat, "updates by the bodies measured (medians printed)")->check(CLI::Range(1, 1000));
  unsigned threads = 0;
  app.add_option("--threads", threads, "GlobalFusion's threads (0: its default)");
  std::size_t move_step = 0;
  app.add_option("--move-step", move_step,
                 "instead of the table: the whole map fused, then moved by 2 cm and 1 deg in steps of this many "
                 "leaves (publish.move_step_leaves); prints each step's wall time");
  CLI11_PARSE(app, argc, argv);
  if (move_step > 0) {
    // Read as the server holds a received map: its checked bytes (the body the steps walk).
    const std::shared_ptr<const HeldMap> held = read_map_file(std::string(MAPMERGE_DATA_DIR) + "/" + map);
    GlobalFusion g(held->resolution());
    if (threads != 0) g.set_threads(threads);
    const Eigen::Matrix4d T0 = Eigen::Matrix4d::Identity();
    double t = wall_ms();
    g.set("r", held, T0);
    g.encode();
    std::printf("map %s: %zu nodes fused in %.0f ms on %u thread(s); moved in steps of %zu leaves:\n", map.c_str(),
                held->num_nodes(), wall_ms() - t, g.threads(), move_step);
    Eigen::Matrix4d T1 = Eigen::Matrix4d::Identity();
    T1.topLeftCorner<3, 3>() = Eigen::AngleAxisd(M_PI / 180.0, Eigen::Vector3d::UnitZ()).toRotationMatrix();
    T1(0, 3) = 0.02;
    // The robot's new map halfway through the move (its last `grow` m along x cut off): fused at
    // once by its difference, the move going on with it. The same update with no move under way,
    // for comparison.
    double x0, y0, z0, x1, y1, z1;
    held->tree()->getMetricMin(x0, y0, z0);
    held->tree()->getMetricMax(x1, y1, z1);
    const Eigen::AlignedBox3d cut_box(Eigen::Vector3d(x0 - 1, y0 - 1, z0 - 1), Eigen::Vector3d(x1 - grow, y1 + 1, z1 + 1));
    const std::vector<std::uint8_t> cut_bytes =
        encode_map(*crop_and_transform(*held->tree(), cut_box, Eigen::Isometry3d::Identity()), Encoding::kOctomapBt);
    const std::shared_ptr<const HeldMap> cut = check_map(cut_bytes.data(), cut_bytes.size(), Encoding::kOctomapBt, DecodeLimits{}).map;
    std::vector<double> steps, encodes;
    double halfway_ms = 0.0;
    std::size_t halfway_cubes = 0;
    std::shared_ptr<const HeldMap> moving = held;
    for (int i = 0; i < 10000; ++i) {
      const bool update = i == 4 && cut;
      if (update) moving = cut;
      t = wall_ms();
      const GlobalFuseResult r = g.set("r", moving, T1, 0.0, move_step);
      (update ? halfway_ms : steps.emplace_back()) = wall_ms() - t;
      if (update) halfway_cubes = r.cubes;
      t = wall_ms();
      g.encode();
      if (!update) encodes.push_back(wall_ms() - t);
      if (!r.moving) break;
    }
    std::printf("%zu steps: step median %.1f ms, max %.1f ms; encode after a step median %.1f ms\n", steps.size(),
                median(steps), *std::max_element(steps.begin(), steps.end()), median(encodes));
    if (cut) {
      GlobalFusion still(held->resolution());
      if (threads != 0) still.set_threads(threads);
      still.set("r", held, T1);
      still.encode();
      t = wall_ms();
      const GlobalFuseResult r = still.set("r", cut, T1);
      const double still_ms = wall_ms() - t;
      std::printf("a new map halfway (last %.1f m cut off): %.1f ms, %zu cubes; the same update with no move: %.1f ms, "
                  "%zu cubes\n", grow, halfway_ms, halfway_cubes, still_ms, r.cubes);
    }
    return 0;
  }
  const auto world = read_octree_file(std::string(MAPMERGE_DATA_DIR) + "/" + map);
  const double res = world->getResolution();
  const unsigned used = threads != 0 ? threads : GlobalFusion(world->getResolution()).threads();
  std::printf("map %s, a robot's map grows by %.1f m per update; wall ms, GlobalFusion on %u thread(s)\n",
              map.c_str(), grow, used);
  std::printf("| N | full re-fusion + prune + encode | GlobalFusion all | update (diff of trees) | update (diff of bodies: walk / place) | encode after it | pose change | encode after it | encode unchanged | provenance | decode robot | sums MB | robot tree MB | robot payload MB |\n");
  std::printf("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n");
  for (const int n : sizes) {
    const auto fleet = make_fleet(*world, n, share, grow, tilt_deg * M_PI / 180.0);
    std::vector<MapInGlobal> placed;
    for (const auto& r : fleet) placed.emplace_back(r.map.get(), r.T_global_robot);
    double t = wall_ms();
    auto full = fuse_maps(placed, res);
    const auto full_bytes = encode_map(*full, Encoding::kOctomapBt);
    const double t_full = wall_ms() - t;
    full.reset();

    GlobalFusion g(res);
    g.set_threads(used);
    t = wall_ms();
    for (std::size_t i = 0; i < fleet.size(); ++i)
      g.set("r" + std::to_string(i), fleet[i].map, fleet[i].T_global_robot, fleet[i].map_body);
    g.encode();
    const double t_all = wall_ms() - t;
    const std::size_t k = fleet.size() / 2;  // a robot in the middle of the fleet
    t = wall_ms();
    const GlobalFuseResult up = g.set("r" + std::to_string(k), fleet[k].grown, fleet[k].T_global_robot);  // no body
    const double t_update = wall_ms() - t;
    g.set("r" + std::to_string(k), fleet[k].map, fleet[k].T_global_robot, fleet[k].map_body);  // back (tree walk)
    t = wall_ms();
    GlobalFuseResult up_bytes =
        g.set("r" + std::to_string(k), fleet[k].grown, fleet[k].T_global_robot, fleet[k].grown_body);
    std::vector<double> update_ms{wall_ms() - t}, walk_ms{up_bytes.diff_s * 1e3}, place_ms{up_bytes.place_s * 1e3};
    t = wall_ms();
    auto encoded_update = g.encode();  // the blocks the grown map changed, the rest copied
    std::vector<double> encode_ms{wall_ms() - t};
    for (int r = 1; r < repeat; ++r) {  // back and grown again, on the bodies
      g.set("r" + std::to_string(k), fleet[k].map, fleet[k].T_global_robot, fleet[k].map_body);
      g.encode();
      t = wall_ms();
      up_bytes = g.set("r" + std::to_string(k), fleet[k].grown, fleet[k].T_global_robot, fleet[k].grown_body);
      update_ms.push_back(wall_ms() - t);
      walk_ms.push_back(up_bytes.diff_s * 1e3);
      place_ms.push_back(up_bytes.place_s * 1e3);
      t = wall_ms();
      encoded_update = g.encode();
      encode_ms.push_back(wall_ms() - t);
    }
    const double t_update_bytes = median(update_ms), t_encode_update = median(encode_ms);
    Eigen::Matrix4d moved = fleet[k].T_global_robot;
    moved(0, 3) += 0.02;
    t = wall_ms();
    g.set("r" + std::to_string(k), fleet[k].grown, moved);
    const double t_pose = wall_ms() - t;
    t = wall_ms();
    const auto encoded = g.encode();  // every block of the moved robot written again
    const double t_encode = wall_ms() - t;
    t = wall_ms();
    const auto again = g.encode();  // nothing changed: every block copied
    const double t_encode_again = wall_ms() - t;
    t = wall_ms();
    const Provenance p = g.provenance();
    const double t_prov = wall_ms() - t;
    const auto payload = encode_map(*fleet[k].grown, Encoding::kOctomapBt);
    t = wall_ms();
    const DecodeResult d = decode_map(payload, Encoding::kOctomapBt, DecodeLimits{});
    const double t_decode = wall_ms() - t;
    std::printf("| %d | %.0f | %.0f | %.1f (%s, %zu cubes) | %.1f (%s: %.1f / %.1f; %zu voxel, %zu block adds) | %.1f (%zu kB) | %.0f | %.1f (%zu kB) | %.1f (%zu kB) | %.0f (%zu voxels) | %.1f | %.1f | %.2f | %.3f |\n", n,
                t_full, t_all, t_update, up.incremental ? "diff" : "full", up.cubes, t_update_bytes,
                up_bytes.from_bodies ? "bytes" : "trees", median(walk_ms), median(place_ms), up_bytes.voxel_updates, up_bytes.block_updates, t_encode_update,
                encoded_update.bt.size() / 1024, t_pose, t_encode, encoded.bt.size() / 1024, t_encode_again,
                again.bt.size() / 1024, t_prov, p.owner.size(), t_decode, g.memory_usage() / 1e6, d.tree ? d.tree->memoryUsage() / 1e6 : 0.0,
                payload.size() / 1e6);
    std::fflush(stdout);
  }
  return 0;
}
