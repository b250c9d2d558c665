// ROS side of the local planner: converts offload_msgs/PlanPath and nav_msgs/GetPlan requests on the
// latest nav_msgs/OccupancyGrid into calls of the ROS-free core. PlanRequestHandler needs no NodeHandle,
// so gtests exercise it without a master; PlannerNode only wires topics, services and parameters.
#pragma once

#include <memory>
#include <mutex>
#include <string>

#include <nav_msgs/GetPlan.h>
#include <nav_msgs/OccupancyGrid.h>
#include <offload_msgs/PlanPath.h>
#include <offload_msgs/PlanTiming.h>
#include <ros/ros.h>

#include "offload_planner_cpp/dijkstra.h"
#include "offload_planner_cpp/map_geometry.h"

namespace offload_planner {

MapGeometry geometryOf(const nav_msgs::MapMetaData& info);

// Empty when the map is usable, else why not.
std::string validateMap(const nav_msgs::OccupancyGrid& map);

// offload_msgs/PlanPath status code for a core status.
std::uint8_t toServiceStatus(PlanStatus status);

class PlanRequestHandler {
 public:
  explicit PlanRequestHandler(const PlannerOptions& options = PlannerOptions()) : options_(options) {}

  // Keeps the previous map and returns false (with the reason) when `map` is malformed.
  bool setMap(const nav_msgs::OccupancyGrid::ConstPtr& map, std::string* error);
  nav_msgs::OccupancyGrid::ConstPtr map() const;

  // Thread safe; each calling thread plans with its own buffers on the map current at the call.
  void handle(const offload_msgs::PlanPath::Request& req, offload_msgs::PlanPath::Response* res) const;

 private:
  PlannerOptions options_;
  mutable std::mutex map_mutex_;
  nav_msgs::OccupancyGrid::ConstPtr map_;
  std::string rejected_;  // why the last rejected map was rejected, for NO_MAP replies
};

class PlannerNode {
 public:
  PlannerNode(ros::NodeHandle& nh, ros::NodeHandle& pnh);

 private:
  void onMap(const nav_msgs::OccupancyGrid::ConstPtr& map);
  bool onPlan(offload_msgs::PlanPath::Request& req, offload_msgs::PlanPath::Response& res);
  bool onMakePlan(nav_msgs::GetPlan::Request& req, nav_msgs::GetPlan::Response& res);
  void serve(const offload_msgs::PlanPath::Request& req, offload_msgs::PlanPath::Response* res);

  std::unique_ptr<PlanRequestHandler> handler_;
  std::string planner_name_;
  ros::Subscriber map_sub_;
  ros::ServiceServer plan_srv_;
  ros::ServiceServer make_plan_srv_;
  ros::Publisher path_pub_;
  ros::Publisher timing_pub_;
};

}  // namespace offload_planner
