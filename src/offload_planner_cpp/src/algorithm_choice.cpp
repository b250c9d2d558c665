// algorithm auto: which exact point-to-point search a request gets (jump points or the default's two waves),
// from a sample of the map around its two ends.
#include "offload_planner_cpp/dijkstra.h"

#include <algorithm>
#include <cstdlib>

namespace offload_planner {

Algorithm DijkstraPlanner::chooseAlgorithm(const PlannerOptions& options, int from, int target) const {
  if (weighted_ || !options.stop_at_goal || from == target) return Algorithm::kDijkstra;
  // Jump point search pays where runs of free cells are long: its cost is the jump points it queues, and a
  // jump point comes with every free cell beside a blocked one. So it counts free/blocked boundaries per
  // free cell (rho) on runs of cells sampled from rows around the two ends. Measured, time of the two waves over jump point
  // search: random maps at rho 0.2, 0.4, 0.5, 0.6, 0.7, 0.8, 1.0 (1000 x 1000, random pairs) 3.2, 3.2,
  // 1.8, 1.4, 1.2, 1.0, 0.8; corner to corner on 2000 x 2000 at rho 0.8: 0.4; maze512-1-0 (rho 2.0) 0.2;
  // 8room_000 (0.55) 1.8; every ROS map (0.02-0.23) 3.3-5.8. Below 0.6 it is jump point search.
  constexpr double kMaxBoundariesPerFreeCell = 0.6;
  // At most 32 rows of 4 runs of 32 cells: a few microseconds, whatever the distance.
  constexpr int kSampledRows = 32;
  constexpr int kRunsPerRow = 4;
  constexpr int kRunCells = 32;
  const int w = width_;
  const int fx = from % w, fy = from / w, tx = target % w, ty = target / w;
  const int margin = std::max(std::abs(fx - tx), std::abs(fy - ty)) / 4 + 8;
  const int x0 = std::max(0, std::min(fx, tx) - margin);
  const int x1 = std::min(w - 1, std::max(fx, tx) + margin);
  const int y0 = std::max(0, std::min(fy, ty) - margin);
  const int y1 = std::min(height_ - 1, std::max(fy, ty) + margin);
  const int rows = std::min(kSampledRows, y1 - y0 + 1);
  const int span = x1 - x0 + 1;
  const int runs = span <= kRunsPerRow * kRunCells ? 1 : kRunsPerRow;
  const int run_cells = runs == 1 ? span : kRunCells;
  std::size_t free = 0;
  std::size_t boundaries = 0;
  for (int k = 0; k < rows; ++k) {
    const int y = y0 + (rows > 1 ? static_cast<int>(static_cast<long long>(k) * (y1 - y0) / (rows - 1)) : 0);
    const std::int8_t* const row = grid_ + static_cast<std::size_t>(y) * w;
    const std::int8_t* const below = y + 1 < height_ ? row + w : row;  // the last row: no boundary below
    for (int r = 0; r < runs; ++r) {
      const int begin = x0 + (runs > 1 ? r * (span - run_cells) / (runs - 1) : 0);
      bool left = passable(y * w + begin);
      for (int x = begin; x < begin + run_cells; ++x) {
        const bool here = passable_[static_cast<std::uint8_t>(row[x])];
        free += here;
        boundaries += (here != left) + (here != passable_[static_cast<std::uint8_t>(below[x])]);
        left = here;
      }
    }
  }
  return static_cast<double>(boundaries) < kMaxBoundariesPerFreeCell * static_cast<double>(free) ? Algorithm::kJps
                                                                                              : Algorithm::kDijkstra;
}

}  // namespace offload_planner
