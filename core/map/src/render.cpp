#include "mapmerge/map/render.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <functional>
#include <limits>

#include "canvas.hpp"
#include "render_views.hpp"

namespace mapmerge {
namespace {

using detail::Canvas;
using detail::Panel;
using detail::Rgb;
using detail::Splat;

const Rgb kBlack{20, 20, 20};
const Rgb kGrey{120, 120, 120};
const Rgb kWhite{255, 255, 255};
const Rgb kUnattributed{150, 150, 150};
constexpr int kMargin = 16;
constexpr int kTitleBand = 64;
constexpr int kLegendBand = 84;
constexpr int kPanelPad = 40;
constexpr float kMaxExpandedLeaf = 16.0F;  ///< occupied leaves wider than this many voxels stay whole  ///< free border inside each panel [px]

/// Viridis-like ramp, t in [0, 1].
Rgb height_colour(double t) {
  static const double stops[][3] = {{68, 1, 84},    {65, 68, 135},  {42, 120, 142},
                                    {34, 168, 132}, {122, 209, 81}, {253, 231, 37}};
  t = std::clamp(t, 0.0, 1.0) * 5.0;
  const int i = std::min(4, static_cast<int>(t));
  const double f = t - i;
  Rgb c{};
  for (int k = 0; k < 3; ++k) c[k] = static_cast<std::uint8_t>(stops[i][k] * (1 - f) + stops[i + 1][k] * f);
  return c;
}

Rgb robot_colour(std::size_t i) {
  static const Rgb palette[] = {{31, 119, 180}, {255, 127, 14}, {44, 160, 44},   {214, 39, 40},
                                {148, 103, 189}, {23, 190, 207}, {227, 119, 194}, {188, 189, 34},
                                {140, 86, 75}};
  return palette[i % (sizeof(palette) / sizeof(palette[0]))];
}

std::string fmt(const char* format, double value) {
  char buf[64];
  std::snprintf(buf, sizeof(buf), format, value);
  return buf;
}

/// The map's voxels as cubes: occupied at full resolution (so provenance can colour each one),
/// free as they are stored (the top-down view only shades their footprint).
struct Scene {
  std::vector<Splat> occupied;
  std::vector<Splat> free;
  Eigen::Vector3d lo = Eigen::Vector3d::Constant(std::numeric_limits<double>::infinity());
  Eigen::Vector3d hi = -lo;
  double ceiling_hidden_above = std::numeric_limits<double>::quiet_NaN();  ///< [m], NaN: none
};

int owner_of(const Provenance& prov, const Eigen::Vector3f& c) {
  const double r = prov.resolution;
  auto key = [r](float v) { return static_cast<octomap::key_type>(std::floor(v / r) + 32768); };
  const auto it = prov.owner.find(octomap::OcTreeKey(key(c.x()), key(c.y()), key(c.z())));
  return it == prov.owner.end() ? -1 : it->second.robot;
}

/// A ceiling is a voxel layer in the top third of the map much denser than the typical layer:
/// leave out everything from the bottom of that dense band up, so both views see inside.
void hide_ceiling(Scene& scene, float res) {
  if (scene.occupied.empty()) return;
  const auto layer = [&](const Splat& s) {
    return static_cast<std::size_t>(std::max(0.0, std::floor((s.centre.z() - scene.lo.z()) / res)));
  };
  std::vector<std::size_t> count;
  for (const Splat& s : scene.occupied) {
    const std::size_t l = layer(s);
    if (l >= count.size()) count.resize(l + 1, 0);
    ++count[l];
  }
  std::vector<std::size_t> sorted = count;
  std::nth_element(sorted.begin(), sorted.begin() + static_cast<long>(sorted.size() / 2), sorted.end());
  const std::size_t median = sorted[sorted.size() / 2];
  const std::size_t top_third = 2 * count.size() / 3;
  const auto peak = std::max_element(count.begin() + static_cast<long>(top_third), count.end());
  if (peak == count.end() || *peak < 3 * median + 16 || count.size() < 12) return;
  std::size_t cut = static_cast<std::size_t>(peak - count.begin());
  while (cut > top_third && 3 * count[cut - 1] > *peak) --cut;
  scene.occupied.erase(std::remove_if(scene.occupied.begin(), scene.occupied.end(),
                                      [&](const Splat& s) { return layer(s) >= cut; }),
                       scene.occupied.end());
  scene.ceiling_hidden_above = scene.lo.z() + static_cast<double>(cut) * res;
}

Scene collect(const octomap::OcTree& tree, const RenderConfig& config, const Provenance* prov) {
  Scene scene;
  const float res = static_cast<float>(tree.getResolution());
  for (auto it = tree.begin_leafs(), end = tree.end_leafs(); it != end; ++it) {
    const float size = static_cast<float>(it.getSize());
    const Eigen::Vector3f c(it.getX(), it.getY(), it.getZ());
    if (!tree.isNodeOccupied(*it)) {
      if (config.show_free) scene.free.push_back({c, size, {}});
      continue;
    }
    // Occupied leaves are drawn voxel by voxel (provenance is per voxel), but a huge pruned leaf
    // is drawn whole: its cost must not grow with its volume.
    if (size > kMaxExpandedLeaf * res) {
      scene.occupied.push_back({c, size, {}});
      scene.lo = scene.lo.cwiseMin((c.array() - 0.5F * size).matrix().cast<double>());
      scene.hi = scene.hi.cwiseMax((c.array() + 0.5F * size).matrix().cast<double>());
      continue;
    }
    const int n = static_cast<int>(std::lround(size / res));
    const Eigen::Vector3f corner = c - Eigen::Vector3f::Constant(0.5F * size - 0.5F * res);
    for (int i = 0; i < n * n * n; ++i) {
      const Eigen::Vector3f v = corner + res * Eigen::Vector3f(i % n, (i / n) % n, i / (n * n));
      scene.occupied.push_back({v, res, {}});
      scene.lo = scene.lo.cwiseMin((v.array() - 0.5F * res).matrix().cast<double>());
      scene.hi = scene.hi.cwiseMax((v.array() + 0.5F * res).matrix().cast<double>());
    }
  }
  if (config.hide_ceiling) hide_ceiling(scene, res);
  for (Splat& s : scene.occupied) {
    if (prov != nullptr) {
      const int robot = owner_of(*prov, s.centre);
      s.colour = robot < 0 ? kUnattributed : robot_colour(static_cast<std::size_t>(robot));
    } else {
      s.colour = height_colour((s.centre.z() - scene.lo.z()) / std::max(1e-6, scene.hi.z() - scene.lo.z()));
    }
  }
  return scene;
}

/// A 1-2-5 length near `metres`.
double nice_length(double metres) {
  const double p = std::pow(10.0, std::floor(std::log10(metres)));
  for (const double m : {5.0, 2.0, 1.0}) {
    if (m * p <= metres) return m * p;
  }
  return p;
}

void draw_scale_bar(Canvas& canvas, const Panel& panel) {
  const double metres = nice_length(0.22 * panel.w / panel.scale);
  const int len = static_cast<int>(std::lround(metres * panel.scale));
  const std::string label = fmt(metres >= 1 ? "%.0f m" : "%.2g m", metres);
  const int x = panel.x + 14, y = panel.y + panel.h - 40;
  canvas.fill_rect(x - 6, y - 6, std::max(len, Canvas::text_width(label, 2)) + 12, 38, kWhite);
  canvas.fill_rect(x, y + 18, len, 5, kBlack);
  canvas.fill_rect(x, y + 12, 2, 16, kBlack);
  canvas.fill_rect(x + len - 2, y + 12, 2, 16, kBlack);
  canvas.text(x, y, label, 2, kBlack);
}

using ViewFn = std::function<Eigen::Vector2d(const Eigen::Vector3d&)>;

void draw_frames(Canvas& canvas, const Panel& panel, const std::vector<RobotFrame>& frames,
                 double length, const ViewFn& view) {
  static const Rgb axis_colour[] = {{230, 30, 30}, {20, 170, 20}, {30, 60, 230}};
  for (const RobotFrame& f : frames) {
    const Eigen::Vector3d o = f.T_global_robot.topRightCorner<3, 1>();
    const Eigen::Vector2d po = panel.to_pixel(view(o));
    for (int a = 0; a < 3; ++a) {
      const Eigen::Vector3d tip = o + length * f.T_global_robot.block<3, 1>(0, a);
      const Eigen::Vector2d pt = panel.to_pixel(view(tip));
      canvas.line(po.x(), po.y(), pt.x(), pt.y(), 6, kWhite);
      canvas.line(po.x(), po.y(), pt.x(), pt.y(), 3, axis_colour[a]);
    }
    canvas.fill_rect(static_cast<int>(po.x()) - 3, static_cast<int>(po.y()) - 3, 7, 7, kBlack);
    const int tx = static_cast<int>(po.x()) + 8, ty = static_cast<int>(po.y()) + 8;
    canvas.fill_rect(tx - 3, ty - 3, Canvas::text_width(f.name, 2) + 6, 20, kWhite);
    canvas.text(tx, ty, f.name, 2, kBlack);
  }
}

void draw_legend(Canvas& canvas, const RenderConfig& config, const Scene& scene,
                 const Provenance* prov) {
  const int y = config.height - kLegendBand + 8;
  int x = kMargin;
  if (prov == nullptr) {
    canvas.text(x, y + 14, "HEIGHT", 2, kBlack);
    x += Canvas::text_width("HEIGHT", 2) + 16;
    const int w = std::min(500, config.width / 3);
    for (int i = 0; i < w; ++i) canvas.fill_rect(x + i, y + 8, 1, 24, height_colour(static_cast<double>(i) / (w - 1)));
    canvas.frame_rect(x - 1, y + 7, w + 2, 26, kGrey);
    for (int k = 0; k <= 4; ++k) {
      const double z = scene.lo.z() + (scene.hi.z() - scene.lo.z()) * k / 4.0;
      const std::string label = fmt("%.1f m", z);
      const int tx = x + (w - 1) * k / 4;
      canvas.fill_rect(tx, y + 32, 1, 5, kBlack);
      canvas.text(tx - Canvas::text_width(label, 2) / 2, y + 40, label, 2, kBlack);
    }
    return;
  }
  canvas.text(x, y + 14, "CONTRIBUTED BY", 2, kBlack);
  x += Canvas::text_width("CONTRIBUTED BY", 2) + 20;
  for (std::size_t i = 0; i <= prov->robots.size(); ++i) {
    const bool last = i == prov->robots.size();
    const std::string name = last ? "unattributed" : prov->robots[i].name;
    canvas.fill_rect(x, y + 10, 22, 22, last ? kUnattributed : robot_colour(i));
    canvas.text(x + 30, y + 14, name, 2, kBlack);
    x += 30 + Canvas::text_width(name, 2) + 28;
  }
}

void draw_title(Canvas& canvas, const octomap::OcTree& tree, const RenderConfig& config,
                const Scene& scene) {
  canvas.text(kMargin, 12, config.title.empty() ? "OctoMap" : config.title, 3, kBlack);
  const Eigen::Vector3d e = scene.occupied.empty() ? Eigen::Vector3d::Zero() : Eigen::Vector3d(scene.hi - scene.lo);
  const std::string info = fmt("resolution %.3g m", tree.getResolution()) + "   " +
                           std::to_string(scene.occupied.size()) + " occupied voxels   " +
                           fmt("%.1f", e.x()) + " x " + fmt("%.1f", e.y()) + " x " + fmt("%.1f m", e.z());
  const std::string ceiling = std::isnan(scene.ceiling_hidden_above)
                                  ? ""
                                  : fmt("   ceiling above %.2f m hidden", scene.ceiling_hidden_above);
  canvas.text(kMargin, 42, info + ceiling, 2, kGrey);
}

/// Where the two panels go: side by side, or stacked when that shows a long map larger. With
/// RenderConfig::height == 0 the picture's height follows the map's shape.
struct Layout {
  int width = 0;
  int height = 0;
  Panel top;
  Panel oblique;
};

Layout make_layout(const RenderConfig& config, const Eigen::Vector2d& top_extent,
                   const Eigen::Vector2d& oblique_extent) {
  constexpr int kPad = 2 * kPanelPad;
  Layout side, stack;
  side.width = stack.width = std::max(config.width, 480);
  const int half = (side.width - 3 * kMargin) / 2;
  const int full = side.width - 2 * kMargin;
  auto fit = [](int w, int h, const Eigen::Vector2d& e) {
    return std::min((w - kPad) / e.x(), (h - kPad) / e.y());
  };
  auto tall = [&](int w, const Eigen::Vector2d& e) {
    return std::clamp(static_cast<int>((w - kPad) * e.y() / e.x()) + kPad, 260, 1100);
  };
  const int fixed = config.height > 0 ? std::max(config.height, 360) - kTitleBand - kLegendBand - kMargin : 0;
  const int side_h = fixed > 0 ? fixed : std::max(tall(half, top_extent), tall(half, oblique_extent));
  side.top = {kMargin, kTitleBand, half, side_h};
  side.oblique = {2 * kMargin + half, kTitleBand, half, side_h};
  side.height = kTitleBand + side_h + kMargin + kLegendBand;
  const int top_h = fixed > 0 ? (fixed - kMargin) / 2 : tall(full, top_extent);
  const int obl_h = fixed > 0 ? (fixed - kMargin) / 2 : tall(full, oblique_extent);
  stack.top = {kMargin, kTitleBand, full, top_h};
  stack.oblique = {kMargin, kTitleBand + top_h + kMargin, full, obl_h};
  stack.height = kTitleBand + top_h + obl_h + 2 * kMargin + kLegendBand;
  const double side_scale = std::min(fit(half, side_h, top_extent), fit(half, side_h, oblique_extent));
  const double stack_scale = std::min(fit(full, top_h, top_extent), fit(full, obl_h, oblique_extent));
  if (fixed == 0) return top_extent.x() > 1.4 * top_extent.y() ? stack : side;  // long maps stack
  return stack_scale > 1.25 * side_scale ? stack : side;
}

void draw_panel_frames(Canvas& canvas, const Layout& layout, bool by_robot) {
  for (const Panel* p : {&layout.top, &layout.oblique}) {
    canvas.fill_rect(p->x, p->y, p->w, p->h, kWhite);
    canvas.frame_rect(p->x, p->y, p->w, p->h, {200, 200, 200});
  }
  canvas.text(layout.top.x + 10, layout.top.y + 10,
              by_robot ? "TOP-DOWN, COLOUR = ROBOT" : "TOP-DOWN, COLOUR = HEIGHT", 2, kGrey);
  canvas.text(layout.oblique.x + 10, layout.oblique.y + 10, "OBLIQUE VIEW", 2, kGrey);
}

/// Bounding box of the occupied voxels' projection by `view`.
template <typename View>
std::pair<Eigen::Vector2d, Eigen::Vector2d> projected_box(const Scene& scene,
                                                          const std::vector<RobotFrame>& frames, View view) {
  Eigen::Vector2d lo = Eigen::Vector2d::Constant(1e30), hi = -lo;
  for (const RobotFrame& f : frames) {
    lo = lo.cwiseMin(view(f.T_global_robot.topRightCorner<3, 1>()));
    hi = hi.cwiseMax(view(f.T_global_robot.topRightCorner<3, 1>()));
  }
  for (int i = 0; i < 8; ++i) {
    const Eigen::Vector3d corner((i & 1) ? scene.hi.x() : scene.lo.x(), (i & 2) ? scene.hi.y() : scene.lo.y(),
                                 (i & 4) ? scene.hi.z() : scene.lo.z());
    lo = lo.cwiseMin(view(corner));
    hi = hi.cwiseMax(view(corner));
  }
  return {lo, hi};
}

}  // namespace

Image render_map(const octomap::OcTree& tree, const RenderConfig& config, const Provenance* provenance) {
  const Scene scene = collect(tree, config, provenance);
  detail::ObliqueCamera camera;
  camera.azimuth = config.azimuth_deg * M_PI / 180.0;
  camera.elevation = config.elevation_deg * M_PI / 180.0;
  const auto top_view = [](const Eigen::Vector3d& p) { return Eigen::Vector2d(p.head<2>()); };
  const auto oblique_view = [&camera](const Eigen::Vector3d& p) {
    return Eigen::Vector2d(camera.project(p).head<2>());
  };
  const bool empty = scene.occupied.empty();
  const auto top_box = empty ? std::make_pair(Eigen::Vector2d(0, 0), Eigen::Vector2d(1, 1))
                             : projected_box(scene, config.frames, top_view);
  const auto oblique_box = empty ? top_box : projected_box(scene, config.frames, oblique_view);
  Layout layout = make_layout(config, top_box.second - top_box.first,
                              oblique_box.second - oblique_box.first);
  Image image(layout.width, layout.height, 250);
  Canvas canvas(image);
  RenderConfig cfg = config;
  cfg.width = layout.width;
  cfg.height = layout.height;
  draw_title(canvas, tree, cfg, scene);
  draw_panel_frames(canvas, layout, provenance != nullptr);
  if (!empty || provenance != nullptr) draw_legend(canvas, cfg, scene, provenance);
  if (empty) {
    canvas.text(layout.top.x + layout.top.w / 2 - 108, layout.top.y + layout.top.h / 2, "EMPTY MAP", 4, kGrey);
    return image;
  }
  fit_panel(layout.top, top_box.first, top_box.second, kPanelPad);
  fit_panel(layout.oblique, oblique_box.first, oblique_box.second, kPanelPad);
  detail::draw_top_down(canvas, layout.top, scene.occupied, scene.free);
  detail::draw_oblique(canvas, layout.oblique, camera, scene.occupied);
  const double axis = 0.08 * (scene.hi - scene.lo).head<2>().maxCoeff();
  const std::pair<const Panel*, ViewFn> views[] = {{&layout.top, top_view}, {&layout.oblique, oblique_view}};
  for (const auto& [panel, view] : views) {
    canvas.clip(panel->x, panel->y, panel->w, panel->h);
    draw_frames(canvas, *panel, cfg.frames, axis, view);
    canvas.unclip();
  }
  draw_scale_bar(canvas, layout.top);
  draw_scale_bar(canvas, layout.oblique);
  return image;
}

}  // namespace mapmerge
