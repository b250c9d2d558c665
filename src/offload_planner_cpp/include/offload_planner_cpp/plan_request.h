// The planning request contract, once, without ROS: map validation, the frame check, request validation,
// world <-> cell conversion and the poses of a returned path. The roscpp planner node and the cloud
// bridge (through the pybind11 module) both call these, so the robot gets the same answer, status and
// numbers whichever side plans.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "offload_planner_cpp/dijkstra.h"
#include "offload_planner_cpp/map_geometry.h"
#include "offload_planner_cpp/plan_status.h"

namespace offload_planner {

// What nav_msgs/OccupancyGrid says about its grid, in plain types.
struct MapInfo {
  std::uint64_t width = 0;
  std::uint64_t height = 0;
  double resolution = 0.0;  // metres per cell
  double origin_x = 0.0;
  double origin_y = 0.0;
  double qx = 0.0, qy = 0.0, qz = 0.0, qw = 1.0;  // origin orientation, any non-zero length
  std::size_t data_size = 0;                      // cells actually present
};

struct Outcome {
  PlanStatus status = PlanStatus::kOk;
  std::string message;  // why, when status is not kOk
  bool ok() const { return status == PlanStatus::kOk; }
};

// Largest side the planner accepts.
constexpr std::uint64_t kMaxMapSide = 100000;

// kOk and the map's geometry in `geometry`, or kInvalidMap and why. `max_cells` bounds the planner's
// memory (8 bytes per cell per planning thread); 0 means no bound beyond kMaxMapSide.
Outcome checkMap(const MapInfo& info, std::uint64_t max_cells, MapGeometry* geometry);

// The NO_MAP answer, naming why the last map was refused if one was.
Outcome noMapOutcome(const std::string& last_rejection);

// An empty frame means the map frame, as RViz's and move_base's callers often leave it; a leading '/'
// is ignored (tf1 style).
bool inMapFrame(const std::string& frame, const std::string& map_frame);

struct StampedPoint {
  std::string frame_id;
  double x = 0.0;
  double y = 0.0;
};

struct CellRequest {
  Outcome outcome;
  Cell start;
  Cell goal;
  double tolerance_cells = 0.0;
};

// Checks a request against the map (frames, finite poses, tolerance, both ends on the grid) and converts
// it to cells. `tolerance_m` is float as in offload_msgs/PlanPath and nav_msgs/GetPlan.
CellRequest resolveRequest(const MapGeometry& geometry, const std::string& map_frame, const StampedPoint& start,
                           const StampedPoint& goal, float tolerance_m);

// A pose as geometry_msgs/Pose holds it.
struct Pose {
  double x = 0.0, y = 0.0, z = 0.0;
  double qx = 0.0, qy = 0.0, qz = 0.0, qw = 1.0;
};

// World poses of a planned path: the first is the caller's start pose; the last is the caller's goal
// pose when the path reached the requested goal cell, else the centre of the cell it reached (a
// tolerance fallback must not claim the blocked goal); every other pose is its cell's centre facing the
// next cell (the last one keeps the heading of the final step).
std::vector<Pose> pathPoses(const MapGeometry& geometry, const std::vector<Cell>& path, const Pose& start,
                            const Pose& goal, bool reached_requested_goal);
// The same poses written to out, out + stride, ... (byte copies: any stride and alignment), so a caller serializing
// them as rows of messages (the cloud bridge's, through the pybind11 module) needs no vector between.
void writePathPoses(const MapGeometry& geometry, const Cell* path, std::size_t n, const Pose& start, const Pose& goal,
                    bool reached_requested_goal, unsigned char* out, std::size_t stride);

}  // namespace offload_planner
