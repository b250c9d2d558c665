// ROS side of the local planner: converts offload_msgs/PlanPath and nav_msgs/GetPlan requests on the
// latest nav_msgs/OccupancyGrid into calls of the ROS-free core and its request contract
// (plan_request.h). PlanRequestHandler needs no NodeHandle, so gtests exercise it without a master;
// PlannerNode only wires topics, services and parameters.
#pragma once

#include <atomic>
#include <cstdint>
#include <deque>
#include <memory>
#include <mutex>
#include <string>
#include <unordered_map>

#include <boost/thread/recursive_mutex.hpp>
#include <diagnostic_updater/diagnostic_updater.h>
#include <dynamic_reconfigure/server.h>
#include <nav_msgs/GetPlan.h>
#include <nav_msgs/OccupancyGrid.h>
#include <offload_msgs/PlanPath.h>
#include <offload_msgs/PlanTiming.h>
#include <ros/callback_queue.h>
#include <ros/ros.h>
#include <offload_planner_cpp/PlannerConfig.h>
#include <std_msgs/UInt64.h>

#include "offload_planner_cpp/dijkstra.h"
#include "offload_planner_cpp/plan_request.h"
#include "offload_planner_cpp/planner_options.h"
#include "offload_planner_cpp/planner_pool.h"

namespace offload_planner {

// The contract's view of a map message.
MapInfo mapInfoOf(const nav_msgs::OccupancyGrid& map);

class PlanRequestHandler {
 public:
  // `max_map_cells` 0: no bound beyond the core's side limit. With `inflation` (metres, planner_options.h),
  // each map is inflated once, when it arrives, and every request plans on the inflated grid.
  explicit PlanRequestHandler(const PlannerOptions& options = PlannerOptions(), std::uint64_t max_map_cells = 0,
                              const InflationParams& inflation = InflationParams())
      : options_(options), max_map_cells_(max_map_cells), inflation_(inflation) {}

  // Keeps the previous map and returns false (with the reason) when `map` is malformed.
  bool setMap(const nav_msgs::OccupancyGrid::ConstPtr& map, std::string* error);
  nav_msgs::OccupancyGrid::ConstPtr map() const;
  // Plans from now on with `parameters` (dynamic_reconfigure): the map in force is inflated again first when the
  // inflation changed, so no plan ever meets a grid inflated for other options. Plans already running finish with
  // the options they began with. The caller has checked `parameters` (parametersProblem).
  void setParameters(const PlannerParameters& parameters);

  // Thread safe; each plan borrows a planner (its search buffers) from the pool, so plans that overlap run in
  // parallel, on the map current at the call. `cancel` (optional), set from another thread, stops the plan with
  // CANCELLED.
  void handle(const offload_msgs::PlanPath::Request& req, offload_msgs::PlanPath::Response* res,
              const std::atomic<bool>* cancel = nullptr) const;
  // Planners made so far (each with its search buffers): the most plans that ran at once.
  std::size_t planners() const { return planners_.planners(); }

 private:
  // `map` inflated for `options` and `inflation`, or nullptr when the inflation is off.
  std::shared_ptr<const std::vector<std::int8_t>> inflated(const nav_msgs::OccupancyGrid& map,
                                                           const MapGeometry& geometry, const PlannerOptions& options,
                                                           const InflationParams& inflation) const;

  std::mutex update_mutex_;   // one new map or new parameters at a time (each inflates outside map_mutex_)
  PlannerOptions options_;
  std::uint64_t max_map_cells_;
  InflationParams inflation_;
  mutable std::mutex map_mutex_;   // what a request reads: the map, its inflated grid, geometry and options
  nav_msgs::OccupancyGrid::ConstPtr map_;
  std::shared_ptr<const std::vector<std::int8_t>> inflated_;  // map_ inflated, when inflation_ is enabled
  MapGeometry geometry_;  // of map_
  std::string rejected_;  // why the last rejected map was rejected, for NO_MAP replies
  mutable PlannerPool planners_;
};

// The plans a caller may cancel, by the request's cancel_id. A cancel that arrives before its plan started
// (topics and services travel apart) is remembered, among the latest kRemembered, so the plan never runs.
class CancelRegistry {
 public:
  static constexpr std::size_t kRemembered = 256;
  // The flag the plan with `id` watches; already set when it was cancelled before it began.
  std::shared_ptr<std::atomic<bool>> begin(std::uint64_t id);
  void end(std::uint64_t id);
  void cancel(std::uint64_t id);
  std::size_t running() const;

 private:
  mutable std::mutex mutex_;
  std::unordered_map<std::uint64_t, std::shared_ptr<std::atomic<bool>>> running_;
  std::deque<std::uint64_t> early_;   // cancelled before they began, oldest first, at most kRemembered
};

// The planner options among a node's private parameters: every node parameter of the core's options table
// (planner_options.h), by its name, type and default; the first problem found, or "" when they are fine.
std::string readPlannerParameters(const ros::NodeHandle& pnh, PlannerParameters* parameters);

// Runs `queue`'s callbacks until the queue is disabled (ros::shutdown disables the global one), waiting up to
// `wait_s` at a time for work. One callback a call: callAvailable would hand every callback waiting at that moment to
// the one thread that woke, so of two plans asked together the second waited behind the first while the other
// serving threads slept (a cancel of the second answered only once the first had ended: CI, stop 47).
void serveQueue(ros::CallbackQueue* queue, double wait_s);

class PlannerNode {
 public:
  PlannerNode(ros::NodeHandle& nh, ros::NodeHandle& pnh);
  // Serves until shutdown: maps on their own thread, so a new map is never stuck behind long plans, and
  // `planning_threads` for requests, so a short plan is not stuck behind long ones either.
  void spin();

 private:
  void onMap(const nav_msgs::OccupancyGrid::ConstPtr& map);
  void onCancel(const std_msgs::UInt64::ConstPtr& msg);
  bool onPlan(offload_msgs::PlanPath::Request& req, offload_msgs::PlanPath::Response& res);
  bool onMakePlan(nav_msgs::GetPlan::Request& req, nav_msgs::GetPlan::Response& res);
  void serve(const offload_msgs::PlanPath::Request& req, offload_msgs::PlanPath::Response* res);
  // /diagnostics: the map the node plans on (size, age, a refused newer one) and how its plans ended.
  void diagnose(diagnostic_updater::DiagnosticStatusWrapper& stat);
  // dynamic_reconfigure (planner_reconfigure.cpp): a change checked by the core's table, refused or in force.
  void reconfigure(offload_planner_cpp::PlannerConfig& config, std::uint32_t level);

  std::unique_ptr<PlanRequestHandler> handler_;
  PlannerParameters parameters_;   // in force; changed by reconfigure() only, under reconfigure_mutex_
  boost::recursive_mutex reconfigure_mutex_;
  std::unique_ptr<dynamic_reconfigure::Server<offload_planner_cpp::PlannerConfig>> reconfigure_server_;
  std::string planner_name_;
  int planning_threads_ = 4;
  static constexpr double kSpinnerWaitS = 2.0;   // a spinner thread's wait for work (spin())
  ros::CallbackQueue map_queue_;
  ros::CallbackQueue cancel_queue_;   // its own thread: a cancel must reach a plan while every planning thread is busy
  CancelRegistry cancels_;
  ros::Subscriber map_sub_;
  ros::Subscriber cancel_sub_;
  ros::ServiceServer plan_srv_;
  ros::ServiceServer make_plan_srv_;
  ros::Publisher path_pub_;
  ros::Publisher timing_pub_;
  diagnostic_updater::Updater diagnostics_;
  ros::Timer diagnostics_timer_;
  std::atomic<std::uint64_t> plans_ok_{0};
  std::atomic<std::uint64_t> plans_refused_{0};   // answered with a status other than OK or CANCELLED
  std::atomic<double> last_plan_ms_{-1.0};
  std::mutex map_problem_mutex_;
  std::string map_problem_;                       // why the last map was refused; empty once one is taken
};

}  // namespace offload_planner
