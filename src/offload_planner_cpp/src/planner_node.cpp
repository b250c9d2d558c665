// Local planner node: Dijkstra on the latest /map, served as ~plan (offload_msgs/PlanPath) and
// ~make_plan (nav_msgs/GetPlan). Parameters and topics are listed in the package README.
#include <ros/ros.h>

#include "offload_planner_cpp/planner_ros.h"

int main(int argc, char** argv) {
  ros::init(argc, argv, "planner");
  ros::NodeHandle nh;
  ros::NodeHandle pnh("~");
  offload_planner::PlannerNode node(nh, pnh);
  // Two threads: a new map is taken in while a long plan runs on the previous one.
  ros::AsyncSpinner spinner(2);
  spinner.start();
  ros::waitForShutdown();
  return 0;
}
