#pragma once
// Number formatting shared by the alignment benches' Markdown tables.
#include <cmath>
#include <cstdio>
#include <string>

namespace mapmerge::bench {

/// `v` with `prec` decimals; "-" for NaN (no value), "inf" for an infinite fitness.
inline std::string fmt(double v, int prec = 3) {
  if (std::isnan(v)) return "-";
  if (std::isinf(v)) return "inf";
  char b[32];
  std::snprintf(b, sizeof b, "%.*f", prec, v);
  return b;
}

}  // namespace mapmerge::bench
