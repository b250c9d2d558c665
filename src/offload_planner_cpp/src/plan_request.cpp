#include "offload_planner_cpp/plan_request.h"

#include <cmath>
#include <cstring>
#include <sstream>

namespace offload_planner {
namespace {

std::string stripSlash(const std::string& frame) {
  return !frame.empty() && frame[0] == '/' ? frame.substr(1) : frame;
}

Outcome fail(PlanStatus status, const std::string& message) { return Outcome{status, message}; }

}  // namespace

const char* statusName(PlanStatus status) {
  switch (status) {
    case PlanStatus::kOk: return "OK";
    case PlanStatus::kNoMap: return "NO_MAP";
    case PlanStatus::kBadFrame: return "BAD_FRAME";
    case PlanStatus::kStartOffMap: return "START_OFF_MAP";
    case PlanStatus::kGoalOffMap: return "GOAL_OFF_MAP";
    case PlanStatus::kStartBlocked: return "START_BLOCKED";
    case PlanStatus::kGoalBlocked: return "GOAL_BLOCKED";
    case PlanStatus::kNoPath: return "NO_PATH";
    case PlanStatus::kInvalidMap: return "INVALID_MAP";
    case PlanStatus::kCloudTimeout: return "CLOUD_TIMEOUT";
    case PlanStatus::kCloudError: return "CLOUD_ERROR";
    case PlanStatus::kInvalidRequest: return "INVALID_REQUEST";
    case PlanStatus::kStaleMap: return "STALE_MAP";
    case PlanStatus::kCancelled: return "CANCELLED";
  }
  return "";
}

Outcome checkMap(const MapInfo& info, std::uint64_t max_cells, MapGeometry* geometry) {
  std::ostringstream why;
  const std::uint64_t cells = info.width * info.height;  // both sides are checked <= 1e5 before use
  if (info.width == 0 || info.height == 0) {
    why << "map is empty (" << info.width << " x " << info.height << ")";
  } else if (info.width > kMaxMapSide || info.height > kMaxMapSide) {
    why << "map of " << info.width << " x " << info.height << " cells is larger than the planner accepts (at most "
        << kMaxMapSide << " cells a side)";
  } else if (cells != info.data_size) {
    why << "map data has " << info.data_size << " cells but " << info.width << " x " << info.height << " = " << cells
        << " were declared";
  } else if (max_cells > 0 && cells > max_cells) {
    why << "map of " << info.width << " x " << info.height << " = " << cells << " cells exceeds the limit of "
        << max_cells << " cells (8 bytes a cell per planning thread); raise ~max_map_cells to accept it";
  } else if (!(info.resolution > 0.0) || !std::isfinite(info.resolution)) {
    why << "map resolution " << info.resolution << " is not a positive number";
  } else if (!std::isfinite(info.origin_x) || !std::isfinite(info.origin_y) || !std::isfinite(info.qx) ||
             !std::isfinite(info.qy) || !std::isfinite(info.qz) || !std::isfinite(info.qw)) {
    why << "map origin is not finite";
  } else if (info.qx * info.qx + info.qy * info.qy + info.qz * info.qz + info.qw * info.qw < 1e-12) {
    why << "map origin orientation is a zero quaternion: it has no heading";
  }
  if (!why.str().empty()) return fail(PlanStatus::kInvalidMap, why.str());
  geometry->resolution = info.resolution;
  geometry->origin_x = info.origin_x;
  geometry->origin_y = info.origin_y;
  geometry->origin_yaw = yawOf(info.qx, info.qy, info.qz, info.qw);
  geometry->width = static_cast<int>(info.width);
  geometry->height = static_cast<int>(info.height);
  return Outcome{};
}

Outcome noMapOutcome(const std::string& last_rejection) {
  std::string message = "no map received yet on the map topic";
  if (!last_rejection.empty()) message += " (last map rejected: " + last_rejection + ")";
  return fail(PlanStatus::kNoMap, message);
}

bool inMapFrame(const std::string& frame, const std::string& map_frame) {
  return frame.empty() || stripSlash(frame) == stripSlash(map_frame);
}

CellRequest resolveRequest(const MapGeometry& geometry, const std::string& map_frame, const StampedPoint& start,
                           const StampedPoint& goal, float tolerance_m) {
  CellRequest request;
  for (const StampedPoint* point : {&start, &goal}) {
    if (!inMapFrame(point->frame_id, map_frame)) {
      request.outcome = fail(PlanStatus::kBadFrame, std::string(point == &start ? "start" : "goal") + " is in frame '" +
                                                        point->frame_id + "' but the map is in '" + map_frame +
                                                        "': transform it to the map frame first");
      return request;
    }
  }
  if (!std::isfinite(start.x) || !std::isfinite(start.y) || !std::isfinite(goal.x) || !std::isfinite(goal.y) ||
      !std::isfinite(tolerance_m) || tolerance_m < 0.0f) {
    request.outcome = fail(PlanStatus::kInvalidRequest,
                           "start and goal must be finite and tolerance a finite number >= 0 metres");
    return request;
  }
  // worldToCell compares in double before converting, so a huge finite point is off the map, not an
  // integer overflow.
  std::ostringstream where;
  if (!geometry.worldToCell(start.x, start.y, &request.start)) {
    where << "start (" << start.x << ", " << start.y << ") m is off the map";
    request.outcome = fail(PlanStatus::kStartOffMap, where.str());
    return request;
  }
  if (!geometry.worldToCell(goal.x, goal.y, &request.goal)) {
    where << "goal (" << goal.x << ", " << goal.y << ") m is off the map";
    request.outcome = fail(PlanStatus::kGoalOffMap, where.str());
    return request;
  }
  request.tolerance_cells = tolerance_m / geometry.resolution;
  return request;
}

void writePathPoses(const MapGeometry& geometry, const Cell* path, std::size_t n, const Pose& start, const Pose& goal,
                    bool reached_requested_goal, unsigned char* out, std::size_t stride) {
  double heading = geometry.origin_yaw;  // of a one-cell path's only step, which never happens
  double qz = std::sin(0.5 * heading), qw = std::cos(0.5 * heading);
  int last_dx = 0, last_dy = 0;  // no step yet: (0, 0) is never one
  const double c = std::cos(geometry.origin_yaw), s = std::sin(geometry.origin_yaw);
  for (std::size_t k = 0; k < n; ++k) {
    Pose pose;
    geometry.cellToWorld(path[k], c, s, &pose.x, &pose.y);
    if (k + 1 < n) {
      // Steps are between cell centres of the grid, so their world heading is the grid heading plus the
      // step's angle in cells. A run of equal steps (most of an 8-connected path) shares one heading: computed
      // once per run, the same bits, not an atan2 and a sincos per pose (the robot's bridge writes every cloud path).
      const int dx = path[k + 1].x - path[k].x, dy = path[k + 1].y - path[k].y;
      if (dx != last_dx || dy != last_dy) {
        heading = geometry.origin_yaw + std::atan2(dy, dx);
        qz = std::sin(0.5 * heading);
        qw = std::cos(0.5 * heading);
        last_dx = dx;
        last_dy = dy;
      }
    }
    pose.qz = qz;
    pose.qw = qw;
    if (k == 0) pose = start;
    else if (k + 1 == n && reached_requested_goal) pose = goal;
    std::memcpy(out + k * stride, &pose, sizeof(Pose));
  }
}

std::vector<Pose> pathPoses(const MapGeometry& geometry, const std::vector<Cell>& path, const Pose& start,
                            const Pose& goal, bool reached_requested_goal) {
  std::vector<Pose> poses(path.size());
  writePathPoses(geometry, path.data(), path.size(), start, goal, reached_requested_goal,
                 reinterpret_cast<unsigned char*>(poses.data()), sizeof(Pose));
  return poses;
}

}  // namespace offload_planner
