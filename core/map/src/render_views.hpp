#pragma once
/// Rasterising octree voxels into the two views of `mapmerge render` (internal).

#include <vector>

#include <Eigen/Core>

#include "canvas.hpp"

namespace mapmerge::detail {

/// One occupied cube to draw: centre [m], edge [m], base colour.
struct Splat {
  Eigen::Vector3f centre;
  float size;
  Rgb colour;
};

/// A rectangle of the picture and the map-to-pixel mapping drawn into it.
struct Panel {
  int x = 0, y = 0, w = 0, h = 0;  ///< pixel rectangle
  double scale = 1.0;               ///< pixels per metre
  Eigen::Vector2d offset{0, 0};     ///< pixel position of view coordinate (0, 0)

  Eigen::Vector2d to_pixel(const Eigen::Vector2d& view) const {
    return {x + offset.x() + scale * view.x(), y + offset.y() - scale * view.y()};
  }
};

/// Orthographic oblique camera: heading `azimuth`, looking down by `elevation` [rad].
struct ObliqueCamera {
  double azimuth = 0.0;
  double elevation = 0.6;
  /// (screen right, screen up) [m] and depth (larger = nearer) [m] of a world point.
  Eigen::Vector3d project(const Eigen::Vector3d& p) const;
};

/// Fits the panel's mapping so that the view-coordinate box [lo, hi] fills it with `pad` px.
void fit_panel(Panel& panel, const Eigen::Vector2d& lo, const Eigen::Vector2d& hi, int pad);

/// Top-down view: free footprints light grey, occupied cubes by their top, hill-shaded.
void draw_top_down(Canvas& canvas, const Panel& panel, const std::vector<Splat>& occupied,
                   const std::vector<Splat>& free);

/// Oblique view: z-buffered cube splats, shaded from the depth buffer's slopes, outlined.
void draw_oblique(Canvas& canvas, const Panel& panel, const ObliqueCamera& camera,
                  const std::vector<Splat>& occupied);

}  // namespace mapmerge::detail
