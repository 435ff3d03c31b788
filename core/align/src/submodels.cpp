#include <algorithm>
#include <cmath>
#include <stdexcept>

#include "mapmerge/align/stages.hpp"

namespace mapmerge::align {
namespace {

struct GridAxis {
  float origin = 0.0F;  ///< first block's lower edge [m]
  float size = 0.0F;    ///< block edge [m]
  float stride = 0.0F;  ///< distance between block origins [m]
  int count = 1;        ///< blocks along the axis
};

GridAxis make_axis(float lo, float hi, float size, float stride) {
  GridAxis a{lo, size, stride, 1};
  const float extent = hi - lo;
  if (extent > size) a.count = 1 + static_cast<int>(std::ceil((extent - size) / stride));
  return a;
}

/// Blocks along an axis containing coordinate v: [first, last].
std::pair<int, int> block_range(const GridAxis& a, float v) {
  const float rel = v - a.origin;
  const int last = std::min(a.count - 1, static_cast<int>(std::floor(rel / a.stride)));
  const int first = std::max(0, static_cast<int>(std::floor((rel - a.size) / a.stride)) + 1);
  return {first, last};
}

/// Ring of a cell (0 = on the border) and its angle around the grid centre: the spiral key.
std::pair<int, double> spiral_key(int i, int j, int k, int nx, int ny, int nz) {
  int ring = std::min({i, nx - 1 - i, j, ny - 1 - j});
  if (nz > 1) ring = std::min({ring, k, nz - 1 - k});
  const double angle = std::atan2(j - (ny - 1) / 2.0, i - (nx - 1) / 2.0);
  return {ring, angle + k * 10.0};
}

}  // namespace

std::vector<Block> make_submodels(const std::vector<Eigen::Vector3f>& points,
                                  const SubmodelConfig& config, double unit) {
  if (points.empty()) return {};
  if (!(config.block_overlap >= 0.0 && config.block_overlap < 0.95))
    throw std::invalid_argument("submodels.block_overlap must be in [0, 0.95)");
  Eigen::Vector3f lo = points.front(), hi = points.front();
  for (const auto& p : points) {
    lo = lo.cwiseMin(p);
    hi = hi.cwiseMax(p);
  }
  const auto size_xy = static_cast<float>(config.block_size * unit);
  const auto size_z = config.grid_3d ? static_cast<float>(config.block_height * unit)
                                     : (hi.z() - lo.z()) + 1.0F;
  const auto keep = static_cast<float>(1.0 - config.block_overlap);
  const GridAxis ax = make_axis(lo.x(), hi.x(), size_xy, size_xy * keep);
  const GridAxis ay = make_axis(lo.y(), hi.y(), size_xy, size_xy * keep);
  const GridAxis az = make_axis(lo.z(), hi.z(), size_z, size_z * keep);
  const int nx = ax.count, ny = ay.count, nz = az.count;

  std::vector<Block> grid(static_cast<std::size_t>(nx) * ny * nz);
  auto cell = [&](int i, int j, int k) -> Block& {
    return grid[(static_cast<std::size_t>(k) * ny + j) * nx + i];
  };
  for (std::size_t idx = 0; idx < points.size(); ++idx) {
    const auto [x0, x1] = block_range(ax, points[idx].x());
    const auto [y0, y1] = block_range(ay, points[idx].y());
    const auto [z0, z1] = block_range(az, points[idx].z());
    for (int k = z0; k <= z1; ++k)
      for (int j = y0; j <= y1; ++j)
        for (int i = x0; i <= x1; ++i) cell(i, j, k).members.push_back(idx);
  }
  struct Keyed {
    std::pair<int, double> key;
    Block block;
  };
  std::vector<Keyed> keyed;
  for (int k = 0; k < nz; ++k)
    for (int j = 0; j < ny; ++j)
      for (int i = 0; i < nx; ++i) {
        Block& b = cell(i, j, k);
        if (b.members.empty()) continue;
        b.min = Eigen::Vector3f(ax.origin + i * ax.stride, ay.origin + j * ay.stride,
                                az.origin + k * az.stride);
        b.max = b.min + Eigen::Vector3f(ax.size, ay.size, az.size);
        keyed.push_back({spiral_key(i, j, k, nx, ny, nz), std::move(b)});
      }
  std::stable_sort(keyed.begin(), keyed.end(),
                   [](const Keyed& a, const Keyed& b) { return a.key < b.key; });
  std::vector<Block> blocks;
  blocks.reserve(keyed.size());
  for (auto& kb : keyed) blocks.push_back(std::move(kb.block));
  return blocks;
}

}  // namespace mapmerge::align
