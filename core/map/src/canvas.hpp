#pragma once
/// Drawing on an Image: rectangles, thick lines and 5x7 bitmap text (internal).

#include <array>
#include <cstdint>
#include <string_view>

#include "mapmerge/map/render.hpp"

namespace mapmerge::detail {

using Rgb = std::array<std::uint8_t, 3>;

class Canvas {
 public:
  explicit Canvas(Image& image) : image_(image), clip_{0, 0, image.width, image.height} {}

  /// Restricts drawing to a rectangle (the whole image after unclip()).
  void clip(int x, int y, int w, int h) { clip_ = {x, y, x + w, y + h}; }
  void unclip() { clip_ = {0, 0, image_.width, image_.height}; }

  void set(int x, int y, const Rgb& c) {
    if (x < clip_[0] || y < clip_[1] || x >= clip_[2] || y >= clip_[3]) return;
    std::uint8_t* p = image_.rgb.data() + (static_cast<std::size_t>(y) * static_cast<std::size_t>(image_.width) +
                                           static_cast<std::size_t>(x)) * 3;
    p[0] = c[0];
    p[1] = c[1];
    p[2] = c[2];
  }
  void fill_rect(int x0, int y0, int w, int h, const Rgb& c);
  void frame_rect(int x0, int y0, int w, int h, const Rgb& c);
  /// A line `thickness` pixels wide.
  void line(double x0, double y0, double x1, double y1, int thickness, const Rgb& c);
  /// Text with its top-left corner at (x, y); glyphs 5x7 scaled by `scale`, in capitals except
  /// a lone "m" (metres) or "x" (times).
  void text(int x, int y, std::string_view s, int scale, const Rgb& c);
  static int text_width(std::string_view s, int scale) {
    return static_cast<int>(s.size()) * 6 * scale - scale;
  }

 private:
  Image& image_;
  std::array<int, 4> clip_;  ///< x0, y0, x1, y1 (exclusive)
};

/// 7 rows of 5 bits (bit 4 = leftmost) for a printable ASCII character; blank if unknown.
const std::array<std::uint8_t, 7>& glyph(char c);

}  // namespace mapmerge::detail
