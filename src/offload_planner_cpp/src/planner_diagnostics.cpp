// The planner node's /diagnostics status (diagnostic_updater): what an operator checks first on a robot whose
// paths stopped coming, the map the node plans on and how its plans ended.
#include <mutex>
#include <string>

#include "offload_planner_cpp/planner_ros.h"

namespace offload_planner {

void PlannerNode::diagnose(diagnostic_updater::DiagnosticStatusWrapper& stat) {
  const auto map = handler_->map();
  std::string problem;
  {
    std::lock_guard<std::mutex> lock(map_problem_mutex_);
    problem = map_problem_;
  }
  if (!map) {
    stat.summary(diagnostic_msgs::DiagnosticStatus::WARN, "no map yet on " + map_sub_.getTopic() +
                                                              (problem.empty() ? "" : ": refused: " + problem));
  } else if (!problem.empty()) {
    stat.summary(diagnostic_msgs::DiagnosticStatus::WARN, "newer map refused, planning on the previous one: " +
                                                              problem);
  } else {
    stat.summaryf(diagnostic_msgs::DiagnosticStatus::OK, "planning on a %u x %u map", map->info.width,
                  map->info.height);
  }
  if (map) {
    stat.addf("map size (cells)", "%u x %u", map->info.width, map->info.height);
    stat.addf("map age (s)", "%.1f", (ros::Time::now() - map->header.stamp).toSec());
  }
  stat.add("plans answered OK", static_cast<unsigned long long>(plans_ok_.load()));
  stat.add("plans refused", static_cast<unsigned long long>(plans_refused_.load()));
  // Each holds search buffers of 16 bytes per cell once it has planned across the map: the most plans run at once.
  stat.add("planners (search buffers)", static_cast<unsigned long long>(handler_->planners()));
  const double last = last_plan_ms_.load();
  if (last >= 0) stat.addf("last planning time (ms)", "%.2f", last);
}

}  // namespace offload_planner
