// algorithm auto: which exact point-to-point search a request gets (jump points, A* on buckets or the default's
// two waves), from a sample of the map around its two ends.
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
  // although jump points were 3.9-6.9x faster on every one.)
  // Measured over whole maps (harness, min of 3 runs, 20 queries a map): every street, room, ROS and corridor
  // map of the shared and held-out sets reads 0.000-0.171, and jump points beat A* on buckets there on all but
  // two (1.3-11.5x; 0.77x and 0.86x on husky_playpen and turtlebot3_world). Random clutter reads 0.19 (5 %),
  // 0.35 (10 %), 0.49 (15 %), 0.61 (20 %), 0.72 (25 %), 0.82 (30 %), 0.92 (35 %): A* on buckets, its band
  // along the straight line, beat jump points 2-4x at every density there (binding, 500 and 2000 a side,
  // corner to corner and 6 random pairs) and the waves up to 20 % (2000 corner to corner: 45 against 89 ms at
  // 15 %, 54 against 72 at 20 %), tied at 25 % and lost beyond (72 against 55 ms at 30 %), and on maze512-1-0
  // (0.75, 1-cell corridors the octile distance says nothing about) it took 3.2x the waves' time.
  constexpr double kJumpPointsBelow = 0.26;  // midway between 0.17 (structured) and 0.35 (10 % random)
  constexpr double kAStarBelow = 0.68;       // midway between 0.61 (20 % random) and 0.72 (25 %, a tie then)
  // Since A* on buckets got 28 % faster (#32, branch bidir) it beats the waves on 25 % and 30 % random clutter
  // too (binding, 2000 a side, corner to corner / 6 random pairs, ms: 25 % 46 / 39 against 61 / 117, 30 % 49 / 47
  // against 54 / 114; 35 % 69 / 70 against 59 / 103, mixed), but maze512-1-0 (0.75 corners per free cell, A*
  // 3.5x the waves) reads in that band. A maze's walls are long, random clutter's obstacles small: corners per
  // blocked cell are 0.75 in the maze, 1.7-2.4 on 20-35 % random clutter. So A* up to midway between 0.82 (30 %)
  // and 0.92 (35 %) where the obstacles are small.
  constexpr double kClutterAStarBelow = 0.87;
  constexpr double kSmallObstaclesAbove = 1.2;  // corners per blocked cell
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
  std::size_t sampled = 0;  // cells of both rows of the runs, free or not
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
      sampled += 2 * static_cast<std::size_t>(run_cells);
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
  const double windows_per_free_cell = 0.5 * static_cast<double>(free);
  const double counted = static_cast<double>(corners);
  if (counted < kJumpPointsBelow * windows_per_free_cell) return Algorithm::kJps;
  if (counted < kAStarBelow * windows_per_free_cell) return Algorithm::kAStar;
  const double windows_per_blocked_cell = 0.5 * static_cast<double>(sampled - free);
  const bool small_obstacles = counted > kSmallObstaclesAbove * windows_per_blocked_cell;
  return small_obstacles && counted < kClutterAStarBelow * windows_per_free_cell ? Algorithm::kAStar
                                                                                 : Algorithm::kDijkstra;
}

}  // namespace offload_planner
