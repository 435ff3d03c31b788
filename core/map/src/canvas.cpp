#include "canvas.hpp"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdio>
#include <memory>

#include <png.h>

#include "mapmerge/map/map_io.hpp"

namespace mapmerge {
namespace detail {

void Canvas::fill_rect(int x0, int y0, int w, int h, const Rgb& c) {
  const int xa = std::max(0, x0);
  const int ya = std::max(0, y0);
  const int xb = std::min(image_.width, x0 + w);
  const int yb = std::min(image_.height, y0 + h);
  for (int y = ya; y < yb; ++y) {
    for (int x = xa; x < xb; ++x) set(x, y, c);
  }
}

void Canvas::frame_rect(int x0, int y0, int w, int h, const Rgb& c) {
  fill_rect(x0, y0, w, 1, c);
  fill_rect(x0, y0 + h - 1, w, 1, c);
  fill_rect(x0, y0, 1, h, c);
  fill_rect(x0 + w - 1, y0, 1, h, c);
}

void Canvas::line(double x0, double y0, double x1, double y1, int thickness, const Rgb& c) {
  const double length = std::hypot(x1 - x0, y1 - y0);
  const int steps = std::max(1, static_cast<int>(std::ceil(length * 2)));
  const int r = thickness / 2;
  for (int i = 0; i <= steps; ++i) {
    const double t = static_cast<double>(i) / steps;
    const int x = static_cast<int>(std::lround(x0 + t * (x1 - x0)));
    const int y = static_cast<int>(std::lround(y0 + t * (y1 - y0)));
    fill_rect(x - r, y - r, thickness, thickness, c);
  }
}

void Canvas::text(int x, int y, std::string_view s, int scale, const Rgb& c) {
  for (std::size_t i = 0; i < s.size(); ++i) {
    // Capitals throughout, except a lone "m" (metres) or "x" (times) between spaces.
    const bool lone = (i == 0 || s[i - 1] == ' ') && (i + 1 == s.size() || s[i + 1] == ' ');
    const char ch = lone && (s[i] == 'm' || s[i] == 'x') ? s[i] : static_cast<char>(std::toupper(static_cast<unsigned char>(s[i])));
    const auto& rows = glyph(ch);
    for (int row = 0; row < 7; ++row) {
      for (int col = 0; col < 5; ++col) {
        if ((rows[static_cast<std::size_t>(row)] >> (4 - col)) & 1) {
          fill_rect(x + col * scale, y + row * scale, scale, scale, c);
        }
      }
    }
    x += 6 * scale;
  }
}

}  // namespace detail

void write_png(const Image& image, const std::string& path) {
  std::unique_ptr<FILE, decltype(&std::fclose)> file(std::fopen(path.c_str(), "wb"), &std::fclose);
  if (!file) throw MapError("cannot write '" + path + "'");
  png_structp png = png_create_write_struct(PNG_LIBPNG_VER_STRING, nullptr, nullptr, nullptr);
  png_infop info = png ? png_create_info_struct(png) : nullptr;
  if (info == nullptr) {
    png_destroy_write_struct(&png, nullptr);
    throw MapError("libpng: out of memory");
  }
  std::vector<png_bytep> rows(static_cast<std::size_t>(image.height));
  for (int y = 0; y < image.height; ++y) {
    rows[static_cast<std::size_t>(y)] = const_cast<png_bytep>(image.pixel(0, y));
  }
  if (setjmp(png_jmpbuf(png))) {  // libpng reports errors by longjmp
    png_destroy_write_struct(&png, &info);
    throw MapError("libpng failed writing '" + path + "'");
  }
  png_init_io(png, file.get());
  png_set_IHDR(png, info, static_cast<png_uint_32>(image.width),
               static_cast<png_uint_32>(image.height), 8, PNG_COLOR_TYPE_RGB, PNG_INTERLACE_NONE,
               PNG_COMPRESSION_TYPE_DEFAULT, PNG_FILTER_TYPE_DEFAULT);
  png_write_info(png, info);
  png_write_image(png, rows.data());
  png_write_end(png, nullptr);
  png_destroy_write_struct(&png, &info);
  if (std::fflush(file.get()) != 0) throw MapError("cannot write '" + path + "'");
}

}  // namespace mapmerge
