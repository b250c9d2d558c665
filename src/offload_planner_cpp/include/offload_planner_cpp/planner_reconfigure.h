// dynamic_reconfigure of the planner node (cfg/Planner.cfg, generated into PlannerConfig): each parameter of the
// .cfg is a node parameter of the core's options table by name, read, checked and written through the table
// (planner_options.h), so a reconfigured value meets exactly the rules a YAML value meets. No master needed: the
// gtests call these directly.
#pragma once

#include <string>

#include <offload_planner_cpp/PlannerConfig.h>

#include "offload_planner_cpp/planner_options.h"

namespace offload_planner {

// `*parameters` with every value of `config`, or the first problem ("<name> must be <rule>, got <value>", the pair
// rule included) and `*parameters` left alone.
std::string parametersFromConfig(const offload_planner_cpp::PlannerConfig& config, PlannerParameters* parameters);

// `*config` holding `parameters`' values (what the node plans with), e.g. after a refused change.
void configFromParameters(const PlannerParameters& parameters, offload_planner_cpp::PlannerConfig* config);

// "algorithm astar, inflation_radius 0.5", the values of `after` that differ from `before` among the .cfg's
// parameters; "" when none do.
std::string changedParameters(const PlannerParameters& before, const PlannerParameters& after);

}  // namespace offload_planner
