// algorithm auto: which exact point-to-point search a request gets (jump points or the default's two waves),
// from a sample of the map around its two ends.
#include "offload_planner_cpp/dijkstra.h"

#include <algorithm>
#include <cstdlib>

namespace offload_planner {

Algorithm DijkstraPlanner::chooseAlgorithm(const PlannerOptions& options, int from, int target) const {
  if (weighted_ || !options.stop_at_goal || from == target) return Algorithm::kDijkstra;
  // Jump point search pays where runs of free cells are long: its cost is the jump points it queues, and a
  // jump point comes with a corner of the obstacles (a forced neighbour appears where a wall ends), not with a
  // straight wall. So it counts corners per free cell: 2 x 2 windows (a cell, its right, below and below-right
  // neighbours) with one or three blocked cells or two diagonal ones, on runs of cells sampled from rows around
  // the two ends. (Boundaries per free cell, the measure before, counted every cell along a straight wall: a
  // folded 4-cell corridor read 0.5-0.6, as cluttered as a 15 % random map, and got the waves on 5 of 20 queries
  // although jump points were 3.9-6.9x faster on every one.) Measured, corners per free cell and time of the two
  // waves over jump point search, per query (min of 2 runs): folded corridors 0.0000-0.0011, 3.9-15x; ROS,
  // MovingAI street and room maps 0.003-0.17, 0.5-43x (median over 4); random maps at 5/10/15 % 0.18/0.35/0.48,
  // 0.9-9.1x/2.9-9.1x/1.9-2.8x; at 20 % 0.61, 1.1-2.0x on 800 x 800 random pairs but 0.43x corner to corner on
  // 2000 x 2000; 25-35 % 0.72-0.92, 0.2-1.4x; maze512-1-0 0.75, 0.24-0.72x. Below 0.55 it is jump point search.
  constexpr double kMaxCornersPerFreeCell = 0.55;
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
  std::size_t corners = 0;
  for (int k = 0; k < rows; ++k) {
    const int y = y0 + (rows > 1 ? static_cast<int>(static_cast<long long>(k) * (y1 - y0) / (rows - 1)) : 0);
    const std::int8_t* const row = grid_ + static_cast<std::size_t>(y) * w;
    const std::int8_t* const below = y + 1 < height_ ? row + w : row;  // the last row: its own copy, no corner
    for (int r = 0; r < runs; ++r) {
      const int begin = x0 + (runs > 1 ? r * (span - run_cells) / (runs - 1) : 0);
      bool left = passable_[static_cast<std::uint8_t>(row[begin])];
      bool left_below = passable_[static_cast<std::uint8_t>(below[begin])];
      free += left + left_below;
      for (int x = begin + 1; x < begin + run_cells; ++x) {
        const bool here = passable_[static_cast<std::uint8_t>(row[x])];
        const bool here_below = passable_[static_cast<std::uint8_t>(below[x])];
        free += here + here_below;
        // Not a corner: all four alike, or two and two split by a straight horizontal or vertical line.
        const bool straight = (left == here && left_below == here_below) || (left == left_below && here == here_below);
        corners += !straight;
        left = here;
        left_below = here_below;
      }
    }
  }
  // free counts the cells of both rows of each window: a sampled row that is all wall (rows sampled at a
  // corridor's period) still sees the free row below it, not zero free cells.
  return static_cast<double>(corners) < kMaxCornersPerFreeCell * 0.5 * static_cast<double>(free) ? Algorithm::kJps
                                                                                                : Algorithm::kDijkstra;
}

}  // namespace offload_planner
