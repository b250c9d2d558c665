#include "offload_planner_cpp/planner_options.h"

#include <charconv>
#include <cmath>
#include <limits>

namespace offload_planner {
namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();
// The largest radius, in cells, the core inflates with (it bounds the inflation's work and memory).
constexpr double kMaxRadiusCells = 1e4;

// Reads and writes one field of PlannerParameters as a number.
#define OFFLOAD_REAL(member) \
  [](const PlannerParameters& p) { return static_cast<double>(p.member); }, \
  [](PlannerParameters& p, double v) { p.member = v; }
#define OFFLOAD_INT(member) \
  [](const PlannerParameters& p) { return static_cast<double>(p.member); }, \
  [](PlannerParameters& p, double v) { p.member = static_cast<int>(v); }
#define OFFLOAD_BOOL(member) \
  [](const PlannerParameters& p) { return p.member ? 1.0 : 0.0; }, \
  [](PlannerParameters& p, double v) { p.member = v != 0.0; }

std::vector<OptionSpec> buildTable() {
  const PlannerOptions o;     // the defaults are the structs' own
  const InflationParams m;
  using T = OptionType;
  constexpr OptionScope kCells = OptionScope::kCells;
  constexpr OptionScope kMetres = OptionScope::kMetres;
  return {
      {"lethal_threshold", T::kInt, kCells, true, double(o.lethal_threshold), 1, 101, false, "occupancy",
       "a cell whose occupancy is at or above this is an obstacle (101: none is)", nullptr, 0,
       OFFLOAD_INT(options.lethal_threshold)},
      {"unknown_is_obstacle", T::kBool, kCells, true, o.unknown_is_obstacle ? 1.0 : 0.0, 0, 1, false, "",
       "unknown (-1) cells are obstacles; false: they cost as free cells", nullptr, 0,
       OFFLOAD_BOOL(options.unknown_is_obstacle)},
      {"goal_tolerance_cells", T::kReal, kCells, false, o.goal_tolerance_cells, 0, kInf, false, "cells",
       "a blocked or unreachable goal is replaced by the nearest reachable free cell within this radius",
       nullptr, 0, OFFLOAD_REAL(options.goal_tolerance_cells)},
      {"stop_at_goal", T::kBool, kCells, false, o.stop_at_goal ? 1.0 : 0.0, 0, 1, false, "",
       "stop when the goal is settled; false explores the whole reachable component", nullptr, 0,
       OFFLOAD_BOOL(options.stop_at_goal)},
      {"cost_factor", T::kReal, kCells, true, o.cost_factor, 0, kInf, false, "",
       "0: every passable cell costs alike; else a move costs its length times the mean of neutral_cost + "
       "cost_factor * occupancy over its two cells (global_planner's model)",
       nullptr, 0, OFFLOAD_REAL(options.cost_factor)},
      {"neutral_cost", T::kReal, kCells, true, o.neutral_cost, 0, kInf, true, "",
       "the weight of a free cell in cost-aware planning", nullptr, 0, OFFLOAD_REAL(options.neutral_cost)},
      {"robot_radius_cells", T::kReal, kCells, false, o.robot_radius_cells, 0, kMaxRadiusCells, false, "cells",
       "inflation: cells this close to an obstacle become obstacles", nullptr, 0,
       OFFLOAD_REAL(options.robot_radius_cells)},
      {"inflation_radius_cells", T::kReal, kCells, false, o.inflation_radius_cells, 0, kMaxRadiusCells, false,
       "cells", "inflation: cells this close to an obstacle get costmap_2d's decaying cost", nullptr, 0,
       OFFLOAD_REAL(options.inflation_radius_cells)},
      {"inflation_decay", T::kReal, kCells, false, o.inflation_decay, 0, kInf, false, "1/cell",
       "inflation: the decay of the inflated cost with distance", nullptr, 0,
       OFFLOAD_REAL(options.inflation_decay)},
      {"algorithm", T::kAlgorithm, kCells, true, double(static_cast<int>(o.algorithm)), 0, kAlgorithmCount - 1,
       false, "",
       "dijkstra: the full wave; astar: the octile heuristic; jps: jump point search (cost_factor 0 only); auto: "
       "the fastest exact one for the plan. Every one returns dijkstra's costs",
       nullptr, 0,
       [](const PlannerParameters& p) { return static_cast<double>(static_cast<int>(p.options.algorithm)); },
       [](PlannerParameters& p, double v) { p.options.algorithm = static_cast<Algorithm>(static_cast<int>(v)); }},
      {"any_angle", T::kBool, kCells, true, o.any_angle ? 1.0 : 0.0, 0, 1, false, "",
       "return the corners of the optimal path pulled tight along lines of sight", nullptr, 0,
       OFFLOAD_BOOL(options.any_angle)},
      {"robot_radius", T::kReal, kMetres, true, m.robot_radius_m, 0, kInf, false, "m",
       "robot_radius_cells in metres (costmap_2d's parameter)", "robot_radius_cells", -1,
       OFFLOAD_REAL(inflation.robot_radius_m)},
      {"inflation_radius", T::kReal, kMetres, true, m.inflation_radius_m, 0, kInf, false, "m",
       "inflation_radius_cells in metres (costmap_2d's parameter)", "inflation_radius_cells", -1,
       OFFLOAD_REAL(inflation.inflation_radius_m)},
      {"cost_scaling_factor", T::kReal, kMetres, true, m.cost_scaling_factor, 0, kInf, false, "1/m",
       "inflation_decay per metre (costmap_2d's parameter and default)", "inflation_decay", 1,
       OFFLOAD_REAL(inflation.cost_scaling_factor)},
  };
}

#undef OFFLOAD_REAL
#undef OFFLOAD_INT
#undef OFFLOAD_BOOL

// The shortest text that reads back as `value` (as Python's repr): 101.0000001 is not shown as 101.
std::string numberText(double value) {
  char text[32];
  const auto end = std::to_chars(text, text + sizeof(text), value).ptr;
  return std::string(text, end);
}

std::string algorithmList() {
  std::string names;
  for (int k = 0; k < kAlgorithmCount; ++k) names += (k ? ", " : "") + std::string(kAlgorithmNames[k]);
  return names;
}

template <class Select>
std::string firstProblem(const PlannerParameters& parameters, Select select) {
  for (const OptionSpec& spec : optionsTable()) {
    if (!select(spec)) continue;
    std::string why = optionProblem(spec, spec.get(parameters));
    if (!why.empty()) return why;
  }
  return "";
}

// The one rule between two options.
std::string pairProblem(const PlannerOptions& options) {
  if (options.algorithm == Algorithm::kJps && options.cost_factor != 0.0) {
    return "algorithm jps is exact only where every passable cell costs the same: cost_factor must be 0, got " +
           numberText(options.cost_factor);
  }
  return "";
}

}  // namespace

const std::vector<OptionSpec>& optionsTable() {
  static const std::vector<OptionSpec> table = buildTable();
  return table;
}

const OptionSpec* findOption(const std::string& name) {
  for (const OptionSpec& spec : optionsTable()) {
    if (name == spec.name) return &spec;
  }
  return nullptr;
}

std::string optionRule(const OptionSpec& spec) {
  switch (spec.type) {
    case OptionType::kBool:
      return "true or false";
    case OptionType::kAlgorithm:
      return "one of " + algorithmList();
    case OptionType::kInt:
      return "an integer in " + numberText(spec.min) + ".." + numberText(spec.max);
    case OptionType::kReal:
      break;
  }
  if (spec.max != kInf) return "a finite number in " + numberText(spec.min) + ".." + numberText(spec.max);
  return std::string("a finite number ") + (spec.min_open ? "> " : ">= ") + numberText(spec.min);
}

std::string optionProblem(const OptionSpec& spec, const std::string& got) {
  return std::string(spec.name) + " must be " + optionRule(spec) + ", got " + got;
}

std::string optionProblem(const OptionSpec& spec, double value) {
  switch (spec.type) {
    case OptionType::kBool:
      return "";
    case OptionType::kAlgorithm:
    case OptionType::kInt:
      if (value >= spec.min && value <= spec.max && value == std::floor(value)) return "";
      return optionProblem(spec, numberText(value));
    case OptionType::kReal:
      break;
  }
  const bool above = spec.min_open ? value > spec.min : value >= spec.min;
  if (std::isfinite(value) && above && value <= spec.max) return "";
  return optionProblem(spec, numberText(value));
}

std::string optionsProblem(const PlannerOptions& options) {
  PlannerParameters parameters;
  parameters.options = options;
  const std::string problem =
      firstProblem(parameters, [](const OptionSpec& spec) { return spec.scope == OptionScope::kCells; });
  return problem.empty() ? pairProblem(options) : problem;
}

std::string parametersProblem(const PlannerParameters& parameters) {
  const std::string problem = firstProblem(parameters, [](const OptionSpec& spec) { return spec.node_parameter; });
  return problem.empty() ? pairProblem(parameters.options) : problem;
}

const char* algorithmName(Algorithm algorithm) {
  const int k = static_cast<int>(algorithm);
  return k >= 0 && k < kAlgorithmCount ? kAlgorithmNames[k] : "unknown";
}

std::string algorithmOf(const std::string& name, Algorithm* out) {
  for (int k = 0; k < kAlgorithmCount; ++k) {
    if (name == kAlgorithmNames[k]) {
      *out = static_cast<Algorithm>(k);
      return "";
    }
  }
  return optionProblem(*findOption("algorithm"), "\"" + name + "\"");
}

std::string optionsInCells(double resolution, const InflationParams& inflation, PlannerOptions* options) {
  if (!(std::isfinite(resolution) && resolution > 0.0)) {
    return "resolution must be a finite number > 0, got " + numberText(resolution);
  }
  PlannerParameters parameters;
  parameters.options = *options;
  parameters.inflation = inflation;
  for (const OptionSpec& spec : optionsTable()) {
    if (spec.scope != OptionScope::kMetres) continue;
    const OptionSpec* cells = findOption(spec.in_cells);
    const double value = spec.get(parameters);
    // Divided, not multiplied by 1 / resolution: the very numbers the nodes computed before the table.
    cells->set(parameters, spec.resolution_power < 0 ? value / resolution : value * resolution);
  }
  *options = parameters.options;
  return "";
}

}  // namespace offload_planner
