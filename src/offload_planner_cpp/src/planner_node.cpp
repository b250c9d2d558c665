// Local planner node: Dijkstra on the latest /map, served as ~plan (offload_msgs/PlanPath) and
// ~make_plan (nav_msgs/GetPlan). Parameters and topics are listed in the package README.
#include <memory>
#include <stdexcept>

#include <ros/ros.h>

#include "offload_planner_cpp/planner_ros.h"

int main(int argc, char** argv) {
  ros::init(argc, argv, "planner");
  ros::NodeHandle nh;
  ros::NodeHandle pnh("~");
  std::unique_ptr<offload_planner::PlannerNode> node;
  try {
    node = std::make_unique<offload_planner::PlannerNode>(nh, pnh);
  } catch (const std::invalid_argument&) {
    return 1;  // the reason is already logged; a non-zero exit tells roslaunch the node failed
  }
  node->spin();
  return 0;
}
