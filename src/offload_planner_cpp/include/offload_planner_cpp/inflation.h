// Inflation of a raw occupancy grid (a map_server map), so a robot with no costmap still keeps its
// distance from obstacles: costmap_2d's inflation layer on the OccupancyGrid scale. No ROS dependency.
#pragma once

#include <cstdint>
#include <vector>

#include "offload_planner_cpp/dijkstra.h"

namespace offload_planner {

// Squared Euclidean distance, in cells between cell centres, from every cell to the nearest cell that is
// not passable under `options` (0 for such a cell; +inf when the grid has none). Exact: Felzenszwalb and
// Huttenlocher's separable transform, O(cells).
void obstacleDistanceSquared(const std::int8_t* grid, int width, int height, const PlannerOptions& options,
                             std::vector<double>* out);

// `grid` with the options' inflation: a passable cell within robot_radius_cells of an obstacle becomes 100
// (an obstacle for any lethal_threshold up to 100); one within inflation_radius_cells gets
// round((lethal_threshold - 1) * exp(-inflation_decay * (d - robot_radius_cells))) when that is higher than
// its own occupancy. That is costmap_2d's curve with its INSCRIBED - 1 mapped to the highest passable
// occupancy, so inflated cells cost more but stay passable. Obstacles and unknown cells keep their values.
void inflate(const std::int8_t* grid, int width, int height, const PlannerOptions& options,
             std::vector<std::int8_t>* out);

}  // namespace offload_planner
