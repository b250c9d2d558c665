// checkPath (path_check.h): the whole reply check in one pass, so the bridge makes one call per cloud plan rather
// than a dozen numpy passes (each cheap, but together 0.1-0.2 ms of the robot's CPU on a cold cache).
#include "offload_planner_cpp/path_check.h"
#include "diagonal_step.h"
#include "segment_walk.h"

#include <algorithm>
#include <cmath>
#include <cstdlib>

namespace offload_planner {

PathCheck checkPath(const std::int8_t* grid, int width, int height, const Cell* cells, std::size_t n, Cell start,
                    Cell reached_goal, bool any_angle, const PlannerOptions& options) {
  PathCheck check;
  // On a large map a path's cells lie far apart in memory (a row apart per vertical step), and the robot's grid is
  // cold when a reply arrives: checked in turn, each cell would wait for its own cache miss. Asked for as they are
  // bounds-checked, the misses overlap.
  for (std::size_t k = 0; k < n; ++k) {
    if (cells[k].x < 0 || cells[k].y < 0 || cells[k].x >= width || cells[k].y >= height) {
      check.problem = PathProblem::kLeavesMap;
      return check;
    }
    __builtin_prefetch(grid + static_cast<std::size_t>(cells[k].y) * width + cells[k].x);
  }
  if (n == 0 || !(cells[0] == start)) {
    check.problem = PathProblem::kWrongStart;
    return check;
  }
  if (!(cells[n - 1] == reached_goal)) {
    check.problem = PathProblem::kWrongEnd;
    return check;
  }
  std::size_t diagonal = 0;
  double euclidean = 0.0;
  for (std::size_t k = 1; k < n; ++k) {   // on the grid, so no overflow
    const int dx = std::abs(cells[k].x - cells[k - 1].x);
    const int dy = std::abs(cells[k].y - cells[k - 1].y);
    if (any_angle) {
      if (dx == 0 && dy == 0) {
        check.problem = PathProblem::kRepeatsCorner;
        return check;
      }
      euclidean += std::hypot(static_cast<double>(dx), static_cast<double>(dy));
    } else if (std::max(dx, dy) != 1) {
      check.problem = PathProblem::kNotEightConnected;
      return check;
    } else {
      diagonal += dx + dy - 1;
    }
  }
  if (!any_angle) {
    // Unit moves, checked as the segment walk would (segment_walk.h's unitMoveClear) without its square root and
    // divisions: about a quarter of the check's time on the robot's every cloud path.
    auto passable = [&](int i) { return isPassable(grid[i], options); };
    for (std::size_t k = 0; k < n; ++k) {
      if (!unitMoveClear(cells[k > 0 ? k - 1 : k], cells[k], width, passable)) {
        check.problem = PathProblem::kBlocked;
        check.index = k > 0 ? k - 1 : 0;
        return check;
      }
    }
    check.length_cells = static_cast<double>(n - 1) - diagonal + kDiagonal * diagonal;
    return check;
  }
  // A single cell is a segment from itself to itself: its cell must be passable.
  const std::size_t segments = n > 1 ? n - 1 : 1;
  for (std::size_t k = 0; k < segments; ++k) {
    if (!segmentClear(grid, width, height, cells[k], cells[n > 1 ? k + 1 : k], options)) {
      check.problem = PathProblem::kBlocked;
      check.index = k;
      return check;
    }
  }
  check.length_cells = euclidean;
  return check;
}

}  // namespace offload_planner
