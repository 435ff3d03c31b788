#include <limits>

#include "mapmerge/align/stages.hpp"

namespace mapmerge::align {

Fitness fitness_from_distances(const std::vector<double>& pair_distances, double d_th,
                               std::size_t n_th) {
  Fitness f;
  double sum = 0.0;
  for (double d : pair_distances) {
    if (d <= d_th) {  // binary weight w_i of Eq. 7
      sum += d;
      ++f.n_w;
    }
  }
  const bool enough = f.n_w >= n_th && f.n_w > 0;
  f.value = enough ? sum / static_cast<double>(f.n_w) : std::numeric_limits<double>::infinity();
  return f;
}

}  // namespace mapmerge::align
