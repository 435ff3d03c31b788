#pragma once
/// Pictures of an octree: a top-down view coloured by height and an oblique 3D view, with a
/// title, a colour bar or robot legend, scale bars in metres and, optionally, robots' frames.

#include <cstdint>
#include <string>
#include <vector>

#include <octomap/OcTree.h>

#include "mapmerge/map/provenance.hpp"

namespace mapmerge {

/// An 8-bit RGB image, rows top to bottom.
struct Image {
  int width = 0;
  int height = 0;
  std::vector<std::uint8_t> rgb;  ///< width * height * 3 bytes

  Image() = default;
  Image(int w, int h, std::uint8_t grey)
      : width(w), height(h), rgb(static_cast<std::size_t>(w) * static_cast<std::size_t>(h) * 3, grey) {}
  const std::uint8_t* pixel(int x, int y) const {
    return rgb.data() + (static_cast<std::size_t>(y) * static_cast<std::size_t>(width) +
                         static_cast<std::size_t>(x)) * 3;
  }
};

/// Settings of render_map().
struct RenderConfig {
  int width = 1800;                 ///< whole picture [px]
  int height = 0;                   ///< whole picture [px]; 0: follow the map's shape
  std::string title;                ///< first line of the title band (e.g. the file name)
  double azimuth_deg = 20.0;        ///< oblique view: camera heading about +z, 0 = looking
                                    ///< along +y from the south; ~20 suits maps long in x [deg]
  double elevation_deg = 40.0;      ///< oblique view: camera angle above the horizon [deg]
  bool show_free = true;            ///< top-down view: shade explored free space light grey
  bool hide_ceiling = true;         ///< leave out a detected ceiling (a dense voxel layer in
                                    ///< the top third) so both views show the rooms
  std::vector<RobotFrame> frames;   ///< robot frames drawn as axes (x red, y green, z blue)
};

/// Renders `tree`. With `provenance`, occupied voxels are coloured by contributing robot (grey
/// when unattributed) and the legend names the robots; otherwise colour encodes height.
Image render_map(const octomap::OcTree& tree, const RenderConfig& config,
                 const Provenance* provenance);

/// Writes `image` as a PNG (libpng). Throws MapError when the file cannot be written.
void write_png(const Image& image, const std::string& path);

}  // namespace mapmerge
