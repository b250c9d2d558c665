#include "offload_planner_cpp/inflation.h"

#include <algorithm>
#include <cmath>
#include <limits>

namespace offload_planner {
namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();

// One dimension of the squared distance transform: d[q] = min_p (q - p)^2 + f[p], by the lower envelope
// of the parabolas rooted at each p with f[p] finite. `v` and `z` are scratch of n and n + 1.
void transform1d(const double* f, double* d, int n, std::vector<int>* v, std::vector<double>* z) {
  int k = -1;
  for (int q = 0; q < n; ++q) {
    if (f[q] == kInf) continue;
    while (k >= 0) {
      const int p = (*v)[k];
      const double s = ((f[q] + double(q) * q) - (f[p] + double(p) * p)) / (2.0 * (q - p));
      if (s > (*z)[k]) {
        ++k;
        (*v)[k] = q;
        (*z)[k] = s;
        break;
      }
      --k;
    }
    if (k < 0) {
      k = 0;
      (*v)[0] = q;
      (*z)[0] = -kInf;
    }
    (*z)[k + 1] = kInf;
  }
  if (k < 0) {
    std::fill(d, d + n, kInf);
    return;
  }
  int j = 0;
  for (int q = 0; q < n; ++q) {
    while ((*z)[j + 1] < q) ++j;
    const int p = (*v)[j];
    d[q] = double(q - p) * (q - p) + f[p];
  }
}

}  // namespace

void obstacleDistanceSquared(const std::int8_t* grid, int width, int height, const PlannerOptions& options,
                             std::vector<double>* out) {
  const std::size_t cells = static_cast<std::size_t>(width) * static_cast<std::size_t>(height);
  out->assign(cells, kInf);
  for (std::size_t i = 0; i < cells; ++i) {
    if (!isPassable(grid[i], options)) (*out)[i] = 0.0;
  }
  const int n = std::max(width, height);
  std::vector<double> f(n), d(n), z(n + 1);
  std::vector<int> v(n);
  for (int x = 0; x < width; ++x) {   // columns
    for (int y = 0; y < height; ++y) f[y] = (*out)[static_cast<std::size_t>(y) * width + x];
    transform1d(f.data(), d.data(), height, &v, &z);
    for (int y = 0; y < height; ++y) (*out)[static_cast<std::size_t>(y) * width + x] = d[y];
  }
  for (int y = 0; y < height; ++y) {  // then rows, in place
    double* row = out->data() + static_cast<std::size_t>(y) * width;
    std::copy(row, row + width, f.begin());
    transform1d(f.data(), row, width, &v, &z);
  }
}

void inflate(const std::int8_t* grid, int width, int height, const PlannerOptions& options,
             std::vector<std::int8_t>* out) {
  const std::size_t cells = static_cast<std::size_t>(width) * static_cast<std::size_t>(height);
  out->assign(grid, grid + cells);
  const double robot = std::max(0.0, options.robot_radius_cells);
  const double reach = std::max(robot, options.inflation_radius_cells);
  if (reach <= 0.0) return;
  std::vector<double> d2;
  obstacleDistanceSquared(grid, width, height, options, &d2);
  const int top = std::min(options.lethal_threshold, 101) - 1;   // the highest passable occupancy
  for (std::size_t i = 0; i < cells; ++i) {
    if (!isPassable(grid[i], options) || d2[i] > reach * reach) continue;
    const double d = std::sqrt(d2[i]);
    if (d <= robot) {
      (*out)[i] = 100;
      continue;
    }
    const double cost = std::round(top * std::exp(-options.inflation_decay * (d - robot)));
    if (cost > (*out)[i]) (*out)[i] = static_cast<std::int8_t>(std::min(cost, double(top)));
  }
}

}  // namespace offload_planner
