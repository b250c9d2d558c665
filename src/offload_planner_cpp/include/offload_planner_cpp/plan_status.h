// The status of a planning request, from the core to every caller: the C++ planner, the ROS node, the
// pybind11 module, the cloud protocol and the bridge all use these codes. The values are the ones
// offload_msgs/PlanPath carries (planner_ros.cpp checks that at compile time, a Python test checks the
// generated message), so no layer translates them.
#pragma once

#include <cstdint>

namespace offload_planner {

enum class PlanStatus : std::uint8_t {
  kOk = 0,
  kNoMap = 1,            // no usable map yet
  kBadFrame = 2,         // start or goal not in the map's frame
  kStartOffMap = 3,
  kGoalOffMap = 4,
  kStartBlocked = 5,
  kGoalBlocked = 6,      // goal in an obstacle and no free cell within tolerance
  kNoPath = 7,           // goal (and every free cell within tolerance) unreachable
  kInvalidMap = 8,       // empty map, data size not width x height, bad resolution or origin
  kCloudTimeout = 9,     // the cloud did not answer in time: plan locally
  kCloudError = 10,      // the cloud answered with an error that is not about the request
  kInvalidRequest = 11,  // non-finite pose, negative tolerance, bad planner options
  kStaleMap = 12,        // only a path on a map older than the one in force (the learner's verdict on an answer)
  kCancelled = 13,       // the caller cancelled the plan (it had its path from the other side): no path
};

// One past the largest code: bindings enumerate 0 .. kPlanStatusCount - 1.
constexpr int kPlanStatusCount = 14;

// The code's name as offload_msgs/PlanPath spells its constant, e.g. "GOAL_BLOCKED"; "" past the end.
const char* statusName(PlanStatus status);

}  // namespace offload_planner
