#include "render_views.hpp"

#include <algorithm>
#include <cmath>
#include <limits>

namespace mapmerge::detail {
namespace {

constexpr float kNone = -std::numeric_limits<float>::infinity();
const Rgb kFreeGrey{228, 228, 232};

/// A per-pixel value buffer over a panel, with the colour that won the pixel.
struct Buffer {
  Buffer(const Panel& panel) : w(panel.w), h(panel.h), value(static_cast<std::size_t>(w * h), kNone),
                               colour(static_cast<std::size_t>(w * h)) {}
  int w, h;
  std::vector<float> value;
  std::vector<Rgb> colour;
  float at(int x, int y) const {
    return x < 0 || y < 0 || x >= w || y >= h ? kNone : value[static_cast<std::size_t>(y * w + x)];
  }
  /// Writes `v` over the square [x0, x0+n) x [y0, y0+n) where it beats the stored value.
  void splat(int x0, int y0, int n, float v, const Rgb& c) {
    for (int y = std::max(0, y0); y < std::min(h, y0 + n); ++y) {
      for (int x = std::max(0, x0); x < std::min(w, x0 + n); ++x) {
        const std::size_t i = static_cast<std::size_t>(y * w + x);
        if (v > value[i]) {
          value[i] = v;
          colour[i] = c;
        }
      }
    }
  }
};

Rgb shade(const Rgb& c, double f) {
  return {static_cast<std::uint8_t>(std::clamp(c[0] * f, 0.0, 255.0)),
          static_cast<std::uint8_t>(std::clamp(c[1] * f, 0.0, 255.0)),
          static_cast<std::uint8_t>(std::clamp(c[2] * f, 0.0, 255.0))};
}

/// Lambert shading from the buffer's slopes (in metres per metre), with silhouette outlines
/// where a neighbour is missing or more than `edge` metres behind.
void compose(Canvas& canvas, const Panel& panel, const Buffer& b, const Eigen::Vector3d& light,
             double edge) {
  const double px = 1.0 / panel.scale;  // metres per pixel
  for (int y = 0; y < b.h; ++y) {
    for (int x = 0; x < b.w; ++x) {
      const float v = b.at(x, y);
      if (v == kNone) continue;
      auto near = [&](int dx, int dy) {
        const float n = b.at(x + dx, y + dy);
        return n == kNone || v - n > edge ? v : n;
      };
      const double gx = (near(1, 0) - near(-1, 0)) / (2 * px);
      const double gy = (near(0, -1) - near(0, 1)) / (2 * px);  // image rows grow downwards
      const Eigen::Vector3d n = Eigen::Vector3d(-gx, -gy, 1.0).normalized();
      double f = 0.55 + 0.5 * std::max(0.0, n.dot(light));
      const bool outline = b.at(x - 1, y) < v - edge || b.at(x + 1, y) < v - edge ||
                           b.at(x, y - 1) < v - edge || b.at(x, y + 1) < v - edge;
      if (outline) f *= 0.55;
      canvas.set(panel.x + x, panel.y + y, shade(b.colour[static_cast<std::size_t>(y * b.w + x)], f));
    }
  }
}

}  // namespace

Eigen::Vector3d ObliqueCamera::project(const Eigen::Vector3d& p) const {
  const double ca = std::cos(azimuth), sa = std::sin(azimuth);
  const double u = ca * p.x() + sa * p.y();   // screen right
  const double v = -sa * p.x() + ca * p.y();  // away from the camera, horizontally
  const double ce = std::cos(elevation), se = std::sin(elevation);
  return {u, p.z() * ce + v * se, p.z() * se - v * ce};
}

void fit_panel(Panel& panel, const Eigen::Vector2d& lo, const Eigen::Vector2d& hi, int pad) {
  const Eigen::Vector2d extent = (hi - lo).cwiseMax(1e-3);
  panel.scale = std::min((panel.w - 2 * pad) / extent.x(), (panel.h - 2 * pad) / extent.y());
  const Eigen::Vector2d mid = 0.5 * (lo + hi);
  panel.offset = {0.5 * panel.w - panel.scale * mid.x(), 0.5 * panel.h + panel.scale * mid.y()};
}

void draw_top_down(Canvas& canvas, const Panel& panel, const std::vector<Splat>& occupied,
                   const std::vector<Splat>& free) {
  Buffer b(panel);
  auto footprint = [&](const Splat& s, float value, const Rgb& c) {
    const Eigen::Vector2d p = panel.to_pixel({s.centre.x() - 0.5 * s.size, s.centre.y() + 0.5 * s.size});
    const int n = std::max(1, static_cast<int>(std::ceil(s.size * panel.scale)));
    b.splat(static_cast<int>(std::floor(p.x())) - panel.x, static_cast<int>(std::floor(p.y())) - panel.y, n,
            value, c);
  };
  for (const Splat& s : free) {
    const Eigen::Vector2d p = panel.to_pixel({s.centre.x() - 0.5 * s.size, s.centre.y() + 0.5 * s.size});
    const int n = std::max(1, static_cast<int>(std::ceil(s.size * panel.scale)));
    canvas.fill_rect(static_cast<int>(std::floor(p.x())), static_cast<int>(std::floor(p.y())), n, n, kFreeGrey);
  }
  for (const Splat& s : occupied) footprint(s, s.centre.z() + 0.5F * s.size, s.colour);
  compose(canvas, panel, b, Eigen::Vector3d(-1, 1, 1.5).normalized(), 1e9);
}

void draw_oblique(Canvas& canvas, const Panel& panel, const ObliqueCamera& camera,
                  const std::vector<Splat>& occupied) {
  Buffer b(panel);
  double voxel = std::numeric_limits<double>::infinity();
  for (const Splat& s : occupied) {
    voxel = std::min(voxel, static_cast<double>(s.size));
    const Eigen::Vector3d q = camera.project(s.centre.cast<double>());
    const Eigen::Vector2d p = panel.to_pixel({q.x(), q.y()});
    const int n = std::max(1, static_cast<int>(std::ceil(1.3 * s.size * panel.scale)));
    b.splat(static_cast<int>(std::lround(p.x() - 0.5 * n)) - panel.x,
            static_cast<int>(std::lround(p.y() - 0.5 * n)) - panel.y, n, static_cast<float>(q.z()),
            s.colour);
  }
  if (occupied.empty()) return;
  const double edge = std::max(3.0 * voxel, 3.0 / panel.scale);
  compose(canvas, panel, b, Eigen::Vector3d(-0.4, 0.5, 1.0).normalized(), edge);
}

}  // namespace mapmerge::detail
