#include "offload_planner_cpp/planner_ros.h"

#include <chrono>
#include <cmath>
#include <sstream>
#include <stdexcept>

namespace offload_planner {
namespace {

using offload_msgs::PlanPath;

std::string stripSlash(const std::string& frame) {
  return !frame.empty() && frame[0] == '/' ? frame.substr(1) : frame;
}

// An empty frame means the map frame, as RViz's and move_base's callers often leave it.
bool inMapFrame(const std::string& frame, const std::string& map_frame) {
  return frame.empty() || stripSlash(frame) == stripSlash(map_frame);
}

}  // namespace

MapGeometry geometryOf(const nav_msgs::MapMetaData& info) {
  MapGeometry g;
  g.resolution = info.resolution;
  g.origin_x = info.origin.position.x;
  g.origin_y = info.origin.position.y;
  const auto& q = info.origin.orientation;
  g.origin_yaw = yawOf(q.x, q.y, q.z, q.w);
  g.width = static_cast<int>(info.width);
  g.height = static_cast<int>(info.height);
  return g;
}

std::string validateMap(const nav_msgs::OccupancyGrid& map) {
  std::ostringstream why;
  const auto& info = map.info;
  if (info.width == 0 || info.height == 0) {
    why << "map is empty (" << info.width << " x " << info.height << ")";
  } else if (static_cast<std::uint64_t>(info.width) * info.height != map.data.size()) {
    why << "map data has " << map.data.size() << " cells but " << info.width << " x " << info.height << " = "
        << static_cast<std::uint64_t>(info.width) * info.height << " were declared";
  } else if (!(info.resolution > 0.0f) || !std::isfinite(info.resolution)) {
    why << "map resolution " << info.resolution << " is not a positive number";
  } else if (!std::isfinite(info.origin.position.x) || !std::isfinite(info.origin.position.y) ||
             !std::isfinite(info.origin.orientation.x) || !std::isfinite(info.origin.orientation.y) ||
             !std::isfinite(info.origin.orientation.z) || !std::isfinite(info.origin.orientation.w)) {
    why << "map origin is not finite";
  } else if (info.width > 100000 || info.height > 100000) {
    why << "map of " << info.width << " x " << info.height << " cells is larger than the planner accepts";
  }
  return why.str();
}

std::uint8_t toServiceStatus(PlanStatus status) {
  switch (status) {
    case PlanStatus::kOk: return PlanPath::Response::OK;
    case PlanStatus::kEmptyMap:
    case PlanStatus::kSizeMismatch: return PlanPath::Response::INVALID_MAP;
    case PlanStatus::kStartOffMap: return PlanPath::Response::START_OFF_MAP;
    case PlanStatus::kGoalOffMap: return PlanPath::Response::GOAL_OFF_MAP;
    case PlanStatus::kStartBlocked: return PlanPath::Response::START_BLOCKED;
    case PlanStatus::kGoalBlocked: return PlanPath::Response::GOAL_BLOCKED;
    case PlanStatus::kNoPath: return PlanPath::Response::NO_PATH;
    case PlanStatus::kInvalidOptions: return PlanPath::Response::INVALID_MAP;
  }
  return PlanPath::Response::INVALID_MAP;
}

bool PlanRequestHandler::setMap(const nav_msgs::OccupancyGrid::ConstPtr& map, std::string* error) {
  const std::string why = map ? validateMap(*map) : std::string("null map");
  std::lock_guard<std::mutex> lock(map_mutex_);
  if (!why.empty()) {
    rejected_ = why;
    if (error) *error = why;
    return false;
  }
  map_ = map;
  return true;
}

nav_msgs::OccupancyGrid::ConstPtr PlanRequestHandler::map() const {
  std::lock_guard<std::mutex> lock(map_mutex_);
  return map_;
}

void PlanRequestHandler::handle(const PlanPath::Request& req, PlanPath::Response* res) const {
  nav_msgs::OccupancyGrid::ConstPtr map;
  std::string rejected;
  {
    std::lock_guard<std::mutex> lock(map_mutex_);
    map = map_;  // a map arriving now replaces map_, while this request keeps planning on its copy
    rejected = rejected_;
  }
  res->path = nav_msgs::Path();
  res->planning_time_s = 0.0;
  res->expansions = 0;
  res->cost_m = 0.0;
  if (!map) {
    res->status = PlanPath::Response::NO_MAP;
    res->message = "no map received yet on the map topic";
    if (!rejected.empty()) res->message += " (last map rejected: " + rejected + ")";
    return;
  }
  res->map_stamp = map->header.stamp;
  const std::string& frame = map->header.frame_id;
  for (const auto* pose : {&req.start, &req.goal}) {
    if (!inMapFrame(pose->header.frame_id, frame)) {
      res->status = PlanPath::Response::BAD_FRAME;
      res->message = std::string(pose == &req.start ? "start" : "goal") + " is in frame '" +
                     pose->header.frame_id + "' but the map is in '" + frame +
                     "': transform it to the map frame first";
      return;
    }
  }
  const auto finite = [](const geometry_msgs::PoseStamped& p) {
    return std::isfinite(p.pose.position.x) && std::isfinite(p.pose.position.y);
  };
  if (!finite(req.start) || !finite(req.goal) || !std::isfinite(req.tolerance) || req.tolerance < 0.0f) {
    res->status = PlanPath::Response::INVALID_REQUEST;
    res->message = "start and goal must be finite and tolerance a finite number >= 0 metres";
    return;
  }

  const MapGeometry geometry = geometryOf(map->info);
  Cell start, goal;
  std::ostringstream where;
  if (!geometry.worldToCell(req.start.pose.position.x, req.start.pose.position.y, &start)) {
    where << "start (" << req.start.pose.position.x << ", " << req.start.pose.position.y << ") m is off the map";
    res->status = PlanPath::Response::START_OFF_MAP;
    res->message = where.str();
    return;
  }
  if (!geometry.worldToCell(req.goal.pose.position.x, req.goal.pose.position.y, &goal)) {
    where << "goal (" << req.goal.pose.position.x << ", " << req.goal.pose.position.y << ") m is off the map";
    res->status = PlanPath::Response::GOAL_OFF_MAP;
    res->message = where.str();
    return;
  }

  PlannerOptions options = options_;
  options.goal_tolerance_cells = req.tolerance / geometry.resolution;
  static thread_local DijkstraPlanner planner;
  const PlanResult result = planner.plan(map->data.data(), map->data.size(), geometry.width, geometry.height,
                                         start, goal, options);
  res->status = toServiceStatus(result.status);
  res->message = result.message;
  res->planning_time_s = result.seconds;
  res->expansions = result.expansions;
  if (!result.ok()) return;

  res->cost_m = result.cost * geometry.resolution;
  res->path.header.frame_id = frame;
  res->path.header.stamp = ros::Time::now();
  res->path.poses.resize(result.path.size());
  for (std::size_t k = 0; k < result.path.size(); ++k) {
    auto& pose = res->path.poses[k];
    pose.header = res->path.header;
    geometry.cellToWorld(result.path[k], &pose.pose.position.x, &pose.pose.position.y);
    pose.pose.orientation.w = 1.0;
  }
  // Start and goal keep the caller's exact poses so the path joins the robot and ends as asked.
  if (result.goal == goal) res->path.poses.back().pose = req.goal.pose;
  res->path.poses.front().pose = req.start.pose;
}

PlannerNode::PlannerNode(ros::NodeHandle& nh, ros::NodeHandle& pnh) {
  PlannerOptions options;
  pnh.param("lethal_threshold", options.lethal_threshold, options.lethal_threshold);
  pnh.param("unknown_is_obstacle", options.unknown_is_obstacle, options.unknown_is_obstacle);
  pnh.param<std::string>("planner_name", planner_name_, "local");
  if (options.lethal_threshold < 1 || options.lethal_threshold > 101) {
    ROS_FATAL("~lethal_threshold must be in 1..101, got %d", options.lethal_threshold);
    throw std::invalid_argument("bad ~lethal_threshold");
  }
  handler_ = std::make_unique<PlanRequestHandler>(options);
  path_pub_ = pnh.advertise<nav_msgs::Path>("path", 1, true);
  timing_pub_ = pnh.advertise<offload_msgs::PlanTiming>("timing", 10);
  map_sub_ = nh.subscribe("map", 1, &PlannerNode::onMap, this);
  plan_srv_ = pnh.advertiseService("plan", &PlannerNode::onPlan, this);
  make_plan_srv_ = pnh.advertiseService("make_plan", &PlannerNode::onMakePlan, this);
  ROS_INFO("planner ready: lethal_threshold %d, unknown cells %s; waiting for a map on %s",
           options.lethal_threshold, options.unknown_is_obstacle ? "blocked" : "free",
           map_sub_.getTopic().c_str());
}

void PlannerNode::onMap(const nav_msgs::OccupancyGrid::ConstPtr& map) {
  std::string error;
  if (!handler_->setMap(map, &error)) {
    ROS_ERROR("rejected map on %s: %s; keeping the previous map", map_sub_.getTopic().c_str(), error.c_str());
    return;
  }
  ROS_INFO("map %u x %u at %.3f m/cell in frame '%s'", map->info.width, map->info.height, map->info.resolution,
           map->header.frame_id.c_str());
}

void PlannerNode::serve(const offload_msgs::PlanPath::Request& req, offload_msgs::PlanPath::Response* res) {
  const auto started = std::chrono::steady_clock::now();
  handler_->handle(req, res);
  offload_msgs::PlanTiming timing;
  timing.header.stamp = ros::Time::now();
  timing.planner = planner_name_;
  timing.status = res->status;
  timing.planning_time_s = res->planning_time_s;
  timing.service_time_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count();
  timing.expansions = res->expansions;
  timing.path_cells = static_cast<std::uint32_t>(res->path.poses.size());
  timing.cost_m = res->cost_m;
  timing.map_stamp = res->map_stamp;
  timing_pub_.publish(timing);
  if (res->status == offload_msgs::PlanPath::Response::OK) {
    path_pub_.publish(res->path);
    ROS_DEBUG("planned %zu poses, %.2f m, in %.2f ms", res->path.poses.size(), res->cost_m,
              res->planning_time_s * 1e3);
  } else {
    ROS_WARN("plan failed (status %u): %s", res->status, res->message.c_str());
  }
}

bool PlannerNode::onPlan(offload_msgs::PlanPath::Request& req, offload_msgs::PlanPath::Response& res) {
  serve(req, &res);
  return true;  // failures travel in res.status so the caller always learns why
}

bool PlannerNode::onMakePlan(nav_msgs::GetPlan::Request& req, nav_msgs::GetPlan::Response& res) {
  offload_msgs::PlanPath::Request plan_req;
  plan_req.start = req.start;
  plan_req.goal = req.goal;
  plan_req.tolerance = req.tolerance;
  offload_msgs::PlanPath::Response plan_res;
  serve(plan_req, &plan_res);
  res.plan = plan_res.path;  // empty on failure, as navfn answers; the reason is logged
  return true;
}

}  // namespace offload_planner
