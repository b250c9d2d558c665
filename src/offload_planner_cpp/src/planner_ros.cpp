#include "offload_planner_cpp/planner_ros.h"

#include "offload_planner_cpp/inflation.h"

#include <time.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <stdexcept>
#include <thread>
#include <vector>

namespace offload_planner {
namespace {

using offload_msgs::PlanPath;

// The core's codes are the service's codes: nothing translates them.
#define OFFLOAD_SAME_CODE(constant, core) \
  static_assert(PlanPath::Response::constant == static_cast<std::uint8_t>(PlanStatus::core), #constant)
OFFLOAD_SAME_CODE(OK, kOk);
OFFLOAD_SAME_CODE(NO_MAP, kNoMap);
OFFLOAD_SAME_CODE(BAD_FRAME, kBadFrame);
OFFLOAD_SAME_CODE(START_OFF_MAP, kStartOffMap);
OFFLOAD_SAME_CODE(GOAL_OFF_MAP, kGoalOffMap);
OFFLOAD_SAME_CODE(START_BLOCKED, kStartBlocked);
OFFLOAD_SAME_CODE(GOAL_BLOCKED, kGoalBlocked);
OFFLOAD_SAME_CODE(NO_PATH, kNoPath);
OFFLOAD_SAME_CODE(INVALID_MAP, kInvalidMap);
OFFLOAD_SAME_CODE(CLOUD_TIMEOUT, kCloudTimeout);
OFFLOAD_SAME_CODE(CLOUD_ERROR, kCloudError);
OFFLOAD_SAME_CODE(INVALID_REQUEST, kInvalidRequest);
OFFLOAD_SAME_CODE(STALE_MAP, kStaleMap);
OFFLOAD_SAME_CODE(CANCELLED, kCancelled);
#undef OFFLOAD_SAME_CODE

StampedPoint pointOf(const geometry_msgs::PoseStamped& pose) {
  return {pose.header.frame_id, pose.pose.position.x, pose.pose.position.y};
}

Pose poseOf(const geometry_msgs::Pose& p) {
  return {p.position.x, p.position.y, p.position.z, p.orientation.x, p.orientation.y, p.orientation.z,
          p.orientation.w};
}

void setStatus(const Outcome& outcome, PlanPath::Response* res) {
  res->status = static_cast<std::uint8_t>(outcome.status);
  res->message = outcome.message;
}

}  // namespace

MapInfo mapInfoOf(const nav_msgs::OccupancyGrid& map) {
  const auto& info = map.info;
  const auto& q = info.origin.orientation;
  MapInfo out;
  out.width = info.width;
  out.height = info.height;
  out.resolution = info.resolution;
  out.origin_x = info.origin.position.x;
  out.origin_y = info.origin.position.y;
  out.qx = q.x;
  out.qy = q.y;
  out.qz = q.z;
  out.qw = q.w;
  out.data_size = map.data.size();
  return out;
}

std::shared_ptr<const std::vector<std::int8_t>> PlanRequestHandler::inflated(const nav_msgs::OccupancyGrid& map,
                                                                             const MapGeometry& geometry,
                                                                             const PlannerOptions& options,
                                                                             const InflationParams& inflation) const {
  if (!inflation.enabled()) return nullptr;
  PlannerOptions in_cells = options;
  optionsInCells(geometry.resolution, inflation, &in_cells);   // checkMap: the resolution is finite and > 0
  auto grid = std::make_shared<std::vector<std::int8_t>>();
  inflate(map.data.data(), static_cast<int>(geometry.width), static_cast<int>(geometry.height), in_cells, grid.get());
  return grid;
}

bool PlanRequestHandler::setMap(const nav_msgs::OccupancyGrid::ConstPtr& map, std::string* error) {
  std::lock_guard<std::mutex> update(update_mutex_);   // options_ and inflation_ stay as they are meanwhile
  MapGeometry geometry;
  const Outcome checked = map ? checkMap(mapInfoOf(*map), max_map_cells_, &geometry)
                              : Outcome{PlanStatus::kInvalidMap, "null map"};
  std::shared_ptr<const std::vector<std::int8_t>> grid;
  if (checked.ok()) grid = inflated(*map, geometry, options_, inflation_);   // outside map_mutex_: requests go on
  std::lock_guard<std::mutex> lock(map_mutex_);
  if (!checked.ok()) {
    rejected_ = checked.message;
    if (error) *error = checked.message;
    return false;
  }
  map_ = map;
  inflated_ = grid;
  geometry_ = geometry;
  return true;
}

nav_msgs::OccupancyGrid::ConstPtr PlanRequestHandler::map() const {
  std::lock_guard<std::mutex> lock(map_mutex_);
  return map_;
}

void PlanRequestHandler::handle(const PlanPath::Request& req, PlanPath::Response* res,
                                const std::atomic<bool>* cancel) const {
  nav_msgs::OccupancyGrid::ConstPtr map;
  std::shared_ptr<const std::vector<std::int8_t>> inflated;
  MapGeometry geometry;
  std::string rejected;
  PlannerOptions options;
  {
    std::lock_guard<std::mutex> lock(map_mutex_);
    map = map_;  // a map arriving now replaces map_, while this request keeps planning on its copy
    inflated = inflated_;
    geometry = geometry_;
    rejected = rejected_;
    options = options_;
  }
  *res = PlanPath::Response();
  if (!map) return setStatus(noMapOutcome(rejected), res);
  res->map_stamp = map->header.stamp;
  const std::string& frame = map->header.frame_id;
  const CellRequest request = resolveRequest(geometry, frame, pointOf(req.start), pointOf(req.goal), req.tolerance);
  if (!request.outcome.ok()) return setStatus(request.outcome, res);

  options.goal_tolerance_cells = request.tolerance_cells;
  options.cancel = cancel;
  const std::int8_t* grid = inflated ? inflated->data() : map->data.data();
  const PlanResult result = planners_.borrow()->plan(grid, map->data.size(), geometry.width, geometry.height,
                                         request.start, request.goal, options);
  setStatus(Outcome{result.status, result.message}, res);
  res->planning_time_s = result.seconds;
  res->expansions = result.expansions;
  if (!result.ok()) return;

  res->cost_m = result.cost * geometry.resolution;
  res->path.header.frame_id = frame;
  res->path.header.stamp = ros::Time::now();
  const std::vector<Pose> poses = pathPoses(geometry, result.path, poseOf(req.start.pose), poseOf(req.goal.pose),
                                            result.goal == request.goal);
  res->path.poses.resize(poses.size());
  for (std::size_t k = 0; k < poses.size(); ++k) {
    auto& out = res->path.poses[k];
    out.header = res->path.header;
    out.pose.position.x = poses[k].x;
    out.pose.position.y = poses[k].y;
    out.pose.position.z = poses[k].z;
    out.pose.orientation.x = poses[k].qx;
    out.pose.orientation.y = poses[k].qy;
    out.pose.orientation.z = poses[k].qz;
    out.pose.orientation.w = poses[k].qw;
  }
}

std::shared_ptr<std::atomic<bool>> CancelRegistry::begin(std::uint64_t id) {
  auto flag = std::make_shared<std::atomic<bool>>(false);
  std::lock_guard<std::mutex> lock(mutex_);
  const auto early = std::find(early_.begin(), early_.end(), id);
  if (early != early_.end()) {
    early_.erase(early);
    flag->store(true);
  }
  running_[id] = flag;
  return flag;
}

void CancelRegistry::end(std::uint64_t id) {
  std::lock_guard<std::mutex> lock(mutex_);
  running_.erase(id);
}

void CancelRegistry::cancel(std::uint64_t id) {
  std::lock_guard<std::mutex> lock(mutex_);
  const auto running = running_.find(id);
  if (running != running_.end()) {
    running->second->store(true);
    return;
  }
  early_.push_back(id);
  if (early_.size() > kRemembered) early_.pop_front();
}

std::size_t CancelRegistry::running() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return running_.size();
}

std::string readPlannerParameters(const ros::NodeHandle& pnh, PlannerParameters* parameters) {
  for (const OptionSpec& spec : optionsTable()) {
    if (!spec.node_parameter) continue;
    double value = spec.get(*parameters);
    switch (spec.type) {
      case OptionType::kBool: {
        bool flag = value != 0.0;
        pnh.param(spec.name, flag, flag);
        value = flag ? 1.0 : 0.0;
        break;
      }
      case OptionType::kInt: {
        int number = static_cast<int>(value);
        pnh.param(spec.name, number, number);
        value = number;
        break;
      }
      case OptionType::kReal:
        pnh.param(spec.name, value, value);
        break;
      case OptionType::kAlgorithm: {
        std::string name = algorithmName(parameters->options.algorithm);
        pnh.param(spec.name, name, name);
        Algorithm algorithm;
        const std::string unknown = algorithmOf(name, &algorithm);
        if (!unknown.empty()) return unknown;
        value = static_cast<double>(static_cast<int>(algorithm));
        break;
      }
    }
    const std::string problem = optionProblem(spec, value);
    if (!problem.empty()) return problem;
    spec.set(*parameters, value);
  }
  return "";
}

PlannerNode::PlannerNode(ros::NodeHandle& nh, ros::NodeHandle& pnh) {
  PlannerParameters parameters;
  const std::string problem = readPlannerParameters(pnh, &parameters);
  if (!problem.empty()) {
    ROS_FATAL("~%s", problem.c_str());
    throw std::invalid_argument("bad planner parameter: " + problem);
  }
  parameters_ = parameters;
  const PlannerOptions& options = parameters.options;
  const InflationParams& inflation = parameters.inflation;
  int max_map_cells = 0;
  pnh.param<std::string>("planner_name", planner_name_, "local");
  pnh.param("planning_threads", planning_threads_, planning_threads_);
  pnh.param("max_map_cells", max_map_cells, 64000000);
  if (planning_threads_ < 1 || max_map_cells < 0) {
    ROS_FATAL("~planning_threads must be >= 1 and ~max_map_cells >= 0 (0: no limit), got %d and %d",
              planning_threads_, max_map_cells);
    throw std::invalid_argument("bad ~planning_threads or ~max_map_cells");
  }
  handler_ = std::make_unique<PlanRequestHandler>(options, static_cast<std::uint64_t>(max_map_cells), inflation);
  path_pub_ = pnh.advertise<nav_msgs::Path>("path", 1, true);
  // A deep queue: a burst of fast plans must not drop timings the learner and the bags rely on.
  timing_pub_ = pnh.advertise<offload_msgs::PlanTiming>("timing", 1000);
  ros::SubscribeOptions map_options = ros::SubscribeOptions::create<nav_msgs::OccupancyGrid>(
      "map", 1, boost::bind(&PlannerNode::onMap, this, boost::placeholders::_1), ros::VoidPtr(), &map_queue_);
  map_sub_ = nh.subscribe(map_options);
  ros::SubscribeOptions cancel_options = ros::SubscribeOptions::create<std_msgs::UInt64>(
      "cancel", 100, boost::bind(&PlannerNode::onCancel, this, boost::placeholders::_1), ros::VoidPtr(),
      &cancel_queue_);
  cancel_sub_ = pnh.subscribe(cancel_options);
  diagnostics_.setHardwareID("none");
  diagnostics_.add("planner", this, &PlannerNode::diagnose);
  double diagnostic_period = 1.0;
  pnh.param("diagnostic_period", diagnostic_period, diagnostic_period);
  diagnostics_timer_ = nh.createTimer(ros::Duration(diagnostic_period > 0 ? diagnostic_period : 1.0),
                                      [this](const ros::TimerEvent&) { diagnostics_.update(); });
  // ~set_parameters, ~parameter_updates (latched, recorded), ~parameter_descriptions: cfg/Planner.cfg's options.
  reconfigure_server_ =
      std::make_unique<dynamic_reconfigure::Server<offload_planner_cpp::PlannerConfig>>(reconfigure_mutex_, pnh);
  reconfigure_server_->setCallback(boost::bind(&PlannerNode::reconfigure, this, boost::placeholders::_1,
                                               boost::placeholders::_2));
  plan_srv_ = pnh.advertiseService("plan", &PlannerNode::onPlan, this);
  make_plan_srv_ = pnh.advertiseService("make_plan", &PlannerNode::onMakePlan, this);
  ROS_INFO("planner ready: %s%s, %s, lethal_threshold %d, unknown cells %s, inflation %.3g m + %.3g m, %d planning "
           "threads, maps up to %d cells; waiting for a map on %s",
           algorithmName(options.algorithm), options.any_angle ? " any-angle" : "",
           options.cost_factor > 0 ? "cost-aware" : "uniform cost", options.lethal_threshold,
           options.unknown_is_obstacle ? "blocked" : "free", inflation.robot_radius_m, inflation.inflation_radius_m,
           planning_threads_, max_map_cells, map_sub_.getTopic().c_str());
}

// One callback a call (planner_ros.h says why).
void serveQueue(ros::CallbackQueue* queue, double wait_s) {
  while (queue->isEnabled()) queue->callOne(ros::WallDuration(wait_s));
}

// roscpp's AsyncSpinner wakes each of its threads every 0.1 s to look for work, and ros::waitForShutdown every
// 0.05 s: with the map, the cancel and four planning threads, 80 wake-ups a second, most of an idle node's CPU
// (4.2 ms/s, a robot's cost whether it plans or not). A queue wakes one waiting thread when a callback arrives, so a
// long wait adds no latency; ros::shutdown disables the global queue, which wakes its threads (the calling thread is
// one of them) to leave, and disabling the node's own queues wakes theirs.
void PlannerNode::spin() {
  const auto serve = [](ros::CallbackQueue* queue) { serveQueue(queue, kSpinnerWaitS); };
  std::vector<std::thread> threads;
  threads.emplace_back(serve, &map_queue_);
  threads.emplace_back(serve, &cancel_queue_);
  for (int i = 1; i < planning_threads_; ++i) threads.emplace_back(serve, ros::getGlobalCallbackQueue());
  serve(ros::getGlobalCallbackQueue());
  map_queue_.disable();
  cancel_queue_.disable();
  ros::getGlobalCallbackQueue()->disable();
  for (auto& thread : threads) thread.join();
}

void PlannerNode::onCancel(const std_msgs::UInt64::ConstPtr& msg) {
  if (msg->data != 0) cancels_.cancel(msg->data);
}

void PlannerNode::onMap(const nav_msgs::OccupancyGrid::ConstPtr& map) {
  std::string error;
  if (!handler_->setMap(map, &error)) {
    ROS_ERROR("rejected map on %s: %s; keeping the previous map", map_sub_.getTopic().c_str(), error.c_str());
    std::lock_guard<std::mutex> lock(map_problem_mutex_);
    map_problem_ = error;
    return;
  }
  {
    std::lock_guard<std::mutex> lock(map_problem_mutex_);
    map_problem_.clear();
  }
  ROS_INFO("map %u x %u at %.3f m/cell in frame '%s'", map->info.width, map->info.height, map->info.resolution,
           map->header.frame_id.c_str());
}

namespace {
// CPU time of the calling thread: what this request cost the robot's CPU, whatever else runs beside it.
double threadCpuSeconds() {
  timespec now{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &now);
  return static_cast<double>(now.tv_sec) + 1e-9 * static_cast<double>(now.tv_nsec);
}
}  // namespace

void PlannerNode::serve(const offload_msgs::PlanPath::Request& req, offload_msgs::PlanPath::Response* res) {
  const auto started = std::chrono::steady_clock::now();
  const double cpu_started = threadCpuSeconds();
  if (req.cancel_id == 0) {
    handler_->handle(req, res);
  } else {
    const auto cancel = cancels_.begin(req.cancel_id);
    handler_->handle(req, res, cancel.get());
    cancels_.end(req.cancel_id);
  }
  res->cpu_s = threadCpuSeconds() - cpu_started;
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
  last_plan_ms_ = res->planning_time_s * 1e3;
  if (res->status == offload_msgs::PlanPath::Response::OK) {
    ++plans_ok_;
  } else if (res->status != offload_msgs::PlanPath::Response::CANCELLED) {
    ++plans_refused_;
  }
  if (res->status == offload_msgs::PlanPath::Response::OK) {
    path_pub_.publish(res->path);
    ROS_DEBUG("planned %zu poses, %.2f m, in %.2f ms", res->path.poses.size(), res->cost_m,
              res->planning_time_s * 1e3);
  } else if (res->status == offload_msgs::PlanPath::Response::CANCELLED) {
    ROS_DEBUG("plan %llu cancelled: %s", static_cast<unsigned long long>(req.cancel_id), res->message.c_str());
  } else {
    ROS_WARN("plan failed (%s): %s", statusName(static_cast<PlanStatus>(res->status)), res->message.c_str());
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
  res.plan = plan_res.path;
  if (plan_res.status != offload_msgs::PlanPath::Response::OK) {
    // Empty on failure, as navfn answers, but in the global frame and stamped now as navfn's is.
    const auto map = handler_->map();
    res.plan.header.frame_id = map ? map->header.frame_id : std::string();
    res.plan.header.stamp = ros::Time::now();
  }
  return true;
}

}  // namespace offload_planner
