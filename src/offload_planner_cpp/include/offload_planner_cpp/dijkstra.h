// Dijkstra on an occupancy grid, with no ROS dependency: the ROS node, the pybind11 module and the cloud
// server all wrap this one core.
//
// Grid convention is nav_msgs/OccupancyGrid: int8, row-major (index y * width + x), -1 unknown, 0..100
// occupancy. Moves are 8-connected with cost 1 and sqrt(2); a diagonal move needs both orthogonal
// neighbours free (no corner cutting), the rules of the MovingAI benchmarks, so optimal lengths match
// theirs exactly.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

namespace offload_planner {

struct Cell {
  int x = 0;
  int y = 0;
  bool operator==(const Cell& other) const { return x == other.x && y == other.y; }
};

struct PlannerOptions {
  // A cell whose occupancy is >= this value is an obstacle (0..100 scale).
  int lethal_threshold = 50;
  // Unknown cells (-1) are obstacles unless this is false.
  bool unknown_is_obstacle = true;
  // In cells. When the goal is blocked or unreachable, plan to the reachable free cell nearest to the
  // goal within this radius instead.
  double goal_tolerance_cells = 0.0;
  // Stop as soon as the goal is settled; false explores the whole reachable component (benchmarks).
  bool stop_at_goal = true;
};

enum class PlanStatus {
  kOk = 0,
  kEmptyMap,
  kSizeMismatch,
  kStartOffMap,
  kGoalOffMap,
  kStartBlocked,
  kGoalBlocked,
  kNoPath,
  kInvalidOptions,
};

// Stable identifier for logs and bindings, e.g. "goal_blocked".
const char* statusName(PlanStatus status);

struct PlanResult {
  PlanStatus status = PlanStatus::kOk;
  std::string message;       // human-readable reason when status != kOk
  std::vector<Cell> path;    // start to goal inclusive; empty unless kOk
  double cost = 0.0;         // path length in cells
  Cell goal;                 // the cell actually reached (differs from the request within tolerance)
  std::uint64_t expansions = 0;  // cells settled
  double seconds = 0.0;      // wall time inside plan()
  bool ok() const { return status == PlanStatus::kOk; }
};

// Keeps its search buffers between calls so repeated plans on one map allocate nothing. Not thread
// safe: use one planner per thread.
class DijkstraPlanner {
 public:
  // `data` holds `size` cells of a width x height grid; `size` must equal width * height.
  PlanResult plan(const std::int8_t* data, std::size_t size, int width, int height, Cell start, Cell goal,
                  const PlannerOptions& options = PlannerOptions());

 private:
  // Runs the search from `start`; returns true when `target` was settled.
  bool search(int start, int target, bool stop_at_target);
  // Walks back from `goal` along settled cells, each step to the neighbour with the smallest distance.
  void tracePath(int goal, std::vector<Cell>* path) const;
  bool passable(int index) const;
  bool settled(int index) const { return mark_[index] == settled_mark_; }
  void beginSearch();

  // Set per call.
  const std::int8_t* grid_ = nullptr;
  int width_ = 0;
  int height_ = 0;
  std::int8_t lethal_ = 50;
  bool unknown_free_ = false;
  std::uint64_t expansions_ = 0;

  // Reused between calls. mark_[i] says whether dist_[i] belongs to the current search (seen_mark_) and
  // whether it is final (settled_mark_); bumping the marks invalidates the whole buffer in O(1).
  std::vector<double> dist_;
  std::vector<std::uint32_t> mark_;
  std::uint32_t seen_mark_ = 0;
  std::uint32_t settled_mark_ = 1;
  std::vector<int> buckets_[3];
};

}  // namespace offload_planner
