// dynamic_reconfigure of the planner node: the .cfg names which of the core's options an operator may change on a
// running robot; the core's table reads, checks and writes each of them, so a reconfigured value meets the rules a
// YAML value meets. A refused change keeps the options in force; an accepted one reaches the next plan (the map in
// force inflated again when the inflation changed) and goes out on ~parameter_updates, which the bag records.
#include "offload_planner_cpp/planner_reconfigure.h"

#include <cstdio>
#include <stdexcept>
#include <string>

#include <boost/any.hpp>
#include <dynamic_reconfigure/config_tools.h>

#include "offload_planner_cpp/planner_ros.h"

namespace offload_planner {
namespace {

using Config = offload_planner_cpp::PlannerConfig;

// The table's number of one .cfg value ("" and *number set), or why there is none (text for a number, an unknown
// algorithm). Bounds are checked by parametersProblem, every row at once.
std::string numberOf(const Config::AbstractParamDescription& param, const OptionSpec& spec, const Config& config,
                     double* number) {
  boost::any value;
  param.getValue(config, value);
  if (param.type == "bool") {
    *number = boost::any_cast<bool>(value) ? 1.0 : 0.0;
  } else if (param.type == "int") {
    *number = boost::any_cast<int>(value);
  } else if (param.type == "double") {
    *number = boost::any_cast<double>(value);
  } else {
    Algorithm algorithm;
    const std::string problem = spec.type == OptionType::kAlgorithm
                                    ? algorithmOf(boost::any_cast<std::string>(value), &algorithm)
                                    : optionProblem(spec, "\"" + boost::any_cast<std::string>(value) + "\"");
    if (!problem.empty()) return problem;
    *number = static_cast<double>(static_cast<int>(algorithm));
  }
  return "";
}

const OptionSpec& rowOf(const Config::AbstractParamDescription& param) {
  const OptionSpec* spec = findOption(param.name);
  if (spec == nullptr || !spec->node_parameter) {
    throw std::logic_error("cfg/Planner.cfg's " + param.name + " is no node parameter of the core's options table");
  }
  return *spec;
}

std::string valueText(const OptionSpec& spec, double value) {
  if (spec.type == OptionType::kAlgorithm) return algorithmName(static_cast<Algorithm>(static_cast<int>(value)));
  if (spec.type == OptionType::kBool) return value != 0.0 ? "true" : "false";
  char text[32];
  std::snprintf(text, sizeof(text), "%.17g", value);
  return text;
}

}  // namespace

std::string parametersFromConfig(const Config& config, PlannerParameters* parameters) {
  PlannerParameters next = *parameters;
  for (const auto& param : Config::__getParamDescriptions__()) {
    const OptionSpec& spec = rowOf(*param);
    double number = 0.0;
    const std::string problem = numberOf(*param, spec, config, &number);
    if (!problem.empty()) return problem;
    spec.set(next, number);
  }
  const std::string problem = parametersProblem(next);   // each row's rule, then the one between jps and cost_factor
  if (problem.empty()) *parameters = next;
  return problem;
}

void configFromParameters(const PlannerParameters& parameters, Config* config) {
  for (const auto& param : Config::__getParamDescriptions__()) {
    const OptionSpec& spec = rowOf(*param);
    const double value = spec.get(parameters);
    dynamic_reconfigure::Config message;
    if (param->type == "bool") {
      dynamic_reconfigure::ConfigTools::appendParameter(message, param->name, value != 0.0);
    } else if (param->type == "int") {
      dynamic_reconfigure::ConfigTools::appendParameter(message, param->name, static_cast<int>(value));
    } else if (param->type == "double") {
      dynamic_reconfigure::ConfigTools::appendParameter(message, param->name, value);
    } else {
      dynamic_reconfigure::ConfigTools::appendParameter(message, param->name, valueText(spec, value));
    }
    param->fromMessage(message, *config);
  }
}

std::string changedParameters(const PlannerParameters& before, const PlannerParameters& after) {
  std::string changed;
  for (const auto& param : Config::__getParamDescriptions__()) {
    const OptionSpec& spec = rowOf(*param);
    if (spec.get(before) == spec.get(after)) continue;
    changed += (changed.empty() ? "" : ", ") + param->name + " " + valueText(spec, spec.get(after));
  }
  return changed;
}

void PlanRequestHandler::setParameters(const PlannerParameters& parameters) {
  std::lock_guard<std::mutex> update(update_mutex_);
  nav_msgs::OccupancyGrid::ConstPtr map;
  MapGeometry geometry;
  {
    std::lock_guard<std::mutex> lock(map_mutex_);
    map = map_;
    geometry = geometry_;
  }
  // A radius that did not change keeps the grid already inflated (an algorithm change costs no inflation).
  std::shared_ptr<const std::vector<std::int8_t>> grid;
  const PlannerOptions& next = parameters.options;
  const bool same_inflation = parameters.inflation.robot_radius_m == inflation_.robot_radius_m &&
                              parameters.inflation.inflation_radius_m == inflation_.inflation_radius_m &&
                              parameters.inflation.cost_scaling_factor == inflation_.cost_scaling_factor &&
                              next.lethal_threshold == options_.lethal_threshold &&
                              next.unknown_is_obstacle == options_.unknown_is_obstacle;
  if (map && !same_inflation) grid = inflated(*map, geometry, next, parameters.inflation);
  std::lock_guard<std::mutex> lock(map_mutex_);
  if (map && same_inflation) grid = inflated_;
  options_ = next;
  inflation_ = parameters.inflation;
  inflated_ = grid;
}

void PlannerNode::reconfigure(Config& config, std::uint32_t level) {
  if (level == ~0u) {   // the server's first call: what the node was started with is in force
    configFromParameters(parameters_, &config);
    return;
  }
  PlannerParameters next = parameters_;
  const std::string problem = parametersFromConfig(config, &next);
  if (!problem.empty()) {
    ROS_WARN("reconfigure refused: %s; the options in force are kept", problem.c_str());
    configFromParameters(parameters_, &config);
    return;
  }
  const std::string changed = changedParameters(parameters_, next);
  if (changed.empty()) return;
  handler_->setParameters(next);
  parameters_ = next;
  ROS_INFO("reconfigured: %s", changed.c_str());
}

}  // namespace offload_planner
