// The cost of one diagonal move on the 8-connected grid, shared by every search of the core (heap searches,
// bucket waves, jump points) so their costs agree to the last bit. Internal to the core: not installed.
#ifndef OFFLOAD_PLANNER_CPP_DIAGONAL_STEP_H
#define OFFLOAD_PLANNER_CPP_DIAGONAL_STEP_H

namespace offload_planner {

constexpr double kDiagonal = 1.4142135623730951;  // sqrt(2)

}  // namespace offload_planner

#endif  // OFFLOAD_PLANNER_CPP_DIAGONAL_STEP_H
