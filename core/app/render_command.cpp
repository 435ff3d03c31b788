// `mapmerge render MAP.(bt|ot) -o out.png [--by-robot PROVENANCE] [--frame NAME:x,y,z,yaw]
//  [--size W[xH]]`: a PNG with a height-coloured top-down view and an oblique 3D view.
#include <cstdio>
#include <iostream>
#include <memory>
#include <sstream>
#include <string>
#include <vector>

#include <Eigen/Geometry>

#include "commands.hpp"
#include "mapmerge/map/map_io.hpp"
#include "mapmerge/map/provenance.hpp"
#include "mapmerge/map/render.hpp"

namespace mapmerge::app {
namespace {

struct RenderOptions {
  std::string map_path;
  std::string out_path;
  std::string provenance_path;      ///< empty: colour by height
  std::vector<std::string> frames;  ///< "NAME:x,y,z,yaw_deg"
  std::string size;                 ///< "W" or "WxH" [px]
  std::string title;
  bool keep_ceiling = false;
  double azimuth_deg = RenderConfig{}.azimuth_deg;
  double elevation_deg = RenderConfig{}.elevation_deg;
};

/// "NAME:x,y,z,yaw_deg" (metres, degrees) -> a frame. Throws CLI::ValidationError.
RobotFrame parse_frame(const std::string& text) {
  const auto colon = text.rfind(':');
  double v[4] = {0, 0, 0, 0};
  char tail = 0;
  if (colon == std::string::npos || colon == 0 ||
      std::sscanf(text.c_str() + colon + 1, "%lf,%lf,%lf,%lf%c", &v[0], &v[1], &v[2], &v[3], &tail) != 4) {
    throw CLI::ValidationError("--frame", "expected NAME:x,y,z,yaw_deg, got '" + text + "'");
  }
  RobotFrame frame;
  frame.name = text.substr(0, colon);
  frame.T_global_robot.topLeftCorner<3, 3>() =
      Eigen::AngleAxisd(v[3] * M_PI / 180.0, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  frame.T_global_robot.topRightCorner<3, 1>() = Eigen::Vector3d(v[0], v[1], v[2]);
  return frame;
}

void parse_size(const std::string& text, RenderConfig& config) {
  int w = 0, h = 0;
  char tail = 0;
  const int n = std::sscanf(text.c_str(), "%dx%d%c", &w, &h, &tail);
  if ((n != 1 && n != 2) || w < 480 || w > 10000 || (n == 2 && (h < 360 || h > 10000))) {
    throw CLI::ValidationError("--size", "expected W or WxH with 480 <= W, 360 <= H <= 10000");
  }
  config.width = w;
  config.height = n == 2 ? h : 0;
}

std::string base_name(const std::string& path) {
  const auto slash = path.find_last_of('/');
  return slash == std::string::npos ? path : path.substr(slash + 1);
}

int run_render(const RenderOptions& opt) {
  RenderConfig config;
  if (!opt.size.empty()) parse_size(opt.size, config);
  config.title = opt.title.empty() ? base_name(opt.map_path) : opt.title;
  config.hide_ceiling = !opt.keep_ceiling;
  config.azimuth_deg = opt.azimuth_deg;
  config.elevation_deg = opt.elevation_deg;
  for (const std::string& f : opt.frames) config.frames.push_back(parse_frame(f));
  try {
    const auto tree = read_octree_file(opt.map_path);
    std::unique_ptr<Provenance> provenance;
    if (!opt.provenance_path.empty()) {
      provenance = std::make_unique<Provenance>(read_provenance(opt.provenance_path));
      if (opt.frames.empty()) config.frames = provenance->robots;  // the robots' own frames
    }
    const Image image = render_map(*tree, config, provenance.get());
    write_png(image, opt.out_path);
    std::cout << opt.out_path << ": " << image.width << "x" << image.height << "\n";
    return 0;
  } catch (const MapError& e) {
    std::cerr << "mapmerge render: " << e.what() << "\n";
    return 1;
  }
}

}  // namespace

void add_render_command(CLI::App& app, int& exit_code) {
  auto opt = std::make_shared<RenderOptions>();
  auto* cmd = app.add_subcommand(
      "render", "draw a map as a PNG: top-down view coloured by height and an oblique 3D view");
  cmd->add_option("map", opt->map_path, "map file (.bt or .ot)")->required();
  cmd->add_option("-o,--output", opt->out_path, "PNG file to write")->required();
  cmd->add_option("--by-robot", opt->provenance_path,
                  "provenance file of a fused map: colour voxels by contributing robot and draw "
                  "each robot's frame");
  cmd->add_option("--frame", opt->frames, "draw a frame NAME:x,y,z,yaw_deg (repeatable)");
  cmd->add_option("--size", opt->size, "picture size W or WxH in pixels (default 1800, height "
                                       "following the map)");
  cmd->add_option("--title", opt->title, "title (default: the map's file name)");
  cmd->add_flag("--keep-ceiling", opt->keep_ceiling, "draw a detected ceiling too");
  cmd->add_option("--azimuth", opt->azimuth_deg, "oblique view heading [deg]");
  cmd->add_option("--elevation", opt->elevation_deg, "oblique view elevation [deg]")->check(CLI::Range(5.0, 90.0));
  cmd->callback([opt, &exit_code] { exit_code = run_render(*opt); });
}

}  // namespace mapmerge::app
