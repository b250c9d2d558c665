// The check of a path someone else planned (the cloud's reply, #31): does it run from the start to the reached goal
// through cells the planner may enter, step by step as the planner steps, and how long is it? One pass over the
// path's cells, never over the map, so the robot's bridge pays O(path) per cloud plan (#30's bridge CPU bar).
#pragma once

#include <cstddef>
#include <cstdint>

#include "offload_planner_cpp/dijkstra.h"

namespace offload_planner {

enum class PathProblem {
  kNone = 0,
  kLeavesMap,          // a cell off the grid
  kWrongStart,         // the first cell is not the start
  kWrongEnd,           // the last cell is not the reached goal
  kRepeatsCorner,      // any-angle: a segment of no length
  kNotEightConnected,  // 8-connected: a step that is not to one of the 8 neighbours
  kBlocked,            // segment `index` enters a blocked cell or cuts a blocked corner
};

struct PathCheck {
  PathProblem problem = PathProblem::kNone;
  std::size_t index = 0;     // the segment of kBlocked
  double length_cells = 0.0;  // the path's length (octile steps, or Euclidean segments when any-angle); 0 on a problem
};

// `cells`: n >= 1 (x, y) pairs. Checks in this order: every cell on the grid, the ends, the steps (any_angle: no
// segment of zero length; else every step to an 8-neighbour), every segment clear by segmentClear's rule.
PathCheck checkPath(const std::int8_t* grid, int width, int height, const Cell* cells, std::size_t n, Cell start,
                    Cell reached_goal, bool any_angle, const PlannerOptions& options);

}  // namespace offload_planner
