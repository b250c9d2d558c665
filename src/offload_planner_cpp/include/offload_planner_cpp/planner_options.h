// The planner's options, once, with no ROS dependency: the options struct the core plans with, the
// nodes' metre parameters, and one table that says for each of them its name, type, default, bounds,
// unit and meaning, how a metre parameter becomes a cell option, and the algorithm names. Every consumer
// (the core's plan(), the roscpp node, the pybind11 module and through it the cloud protocol, bridge and
// rospy bridge node) validates and converts with the functions below and nothing else, in one wording:
// "<name> must be <rule>, got <value>".
//
// A new planner mode is a field of PlannerOptions, a row of the table (planner_options.cpp) and, for a
// choice, a name in kAlgorithmNames; the node parameters, the binding's keywords of validate_options and
// options_table() follow.
#pragma once

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

namespace offload_planner {

// The value of an algorithm is its index in kAlgorithmNames (and the wire protocol's algorithm code).
// kJps, jump point search, is exact only where every passable cell costs the same (cost_factor 0); kAuto
// picks, per plan, the fastest exact search the plan allows (see dijkstra.h).
enum class Algorithm : std::uint8_t { kDijkstra = 0, kAStar = 1, kJps = 2, kAuto = 3 };
constexpr const char* kAlgorithmNames[] = {"dijkstra", "astar", "jps", "auto"};
constexpr int kAlgorithmCount = static_cast<int>(sizeof(kAlgorithmNames) / sizeof(kAlgorithmNames[0]));
static_assert(static_cast<int>(Algorithm::kAuto) == kAlgorithmCount - 1, "one name per Algorithm, in order");

// The options of one plan. The defaults written here are the table's defaults.
struct PlannerOptions {
  // A cell whose occupancy is >= this value is an obstacle (0..100 scale).
  int lethal_threshold = 50;
  // Unknown cells (-1) are obstacles unless this is false.
  bool unknown_is_obstacle = true;
  // In cells. When the goal is blocked or unreachable, plan to the reachable free cell nearest to the
  // goal within this radius instead.
  double goal_tolerance_cells = 0.0;
  // Stop as soon as the goal is settled; false explores the whole reachable component (benchmarks).
  bool stop_at_goal = true;
  // Set to true by another thread, it stops the plan within a few thousand expansions with kCancelled:
  // a caller that already has its path (from the other side) frees the CPU for the next request. Not an
  // option of the table: a run-time handle.
  const std::atomic<bool>* cancel = nullptr;
  // kAStar settles only the cells the octile heuristic cannot rule out; kJps expands only jump points
  // (uniform cost only); kAuto, the default, picks jump points or the waves per plan (algorithm_choice.cpp).
  // Every one returns kDijkstra's costs.
  Algorithm algorithm = Algorithm::kAuto;
  // Return the corners of a path whose segments may run at any angle (see dijkstra.h).
  bool any_angle = false;
  // 0: every passable cell costs alike (the default; exact on MovingAI). Else cost-aware with
  // w = neutral_cost + cost_factor * occupancy (unknown passable cells count as occupancy 0).
  double cost_factor = 0.0;
  double neutral_cost = 50.0;
  // In cells, measured between cell centres. Cells within robot_radius_cells of an obstacle become
  // obstacles; cells within inflation_radius_cells get occupancy 99 * exp(-inflation_decay * (d - robot
  // radius)) if that is higher than their own (costmap_2d's inflation layer on the 0..100 scale).
  double robot_radius_cells = 0.0;
  double inflation_radius_cells = 0.0;
  double inflation_decay = 0.5;   // per cell: costmap_2d's default 10 per metre at 5 cm cells
};

// Inflation in metres, as costmap_2d's parameters and the nodes' ~robot_radius, ~inflation_radius and
// ~cost_scaling_factor: converted to cells with each map's resolution (optionsInCells).
struct InflationParams {
  double robot_radius_m = 0.0;
  double inflation_radius_m = 0.0;
  double cost_scaling_factor = 10.0;   // per metre
  bool enabled() const { return robot_radius_m > 0.0 || inflation_radius_m > 0.0; }
};

// What a node is configured with: the plan options and the inflation in metres.
struct PlannerParameters {
  PlannerOptions options;
  InflationParams inflation;
};

enum class OptionType : std::uint8_t { kBool, kInt, kReal, kAlgorithm };

// kCells: an option of one plan (PlannerOptions), the pybind11 module's keyword of that name.
// kMetres: a node parameter in metres (InflationParams), converted to the cell option `in_cells`.
enum class OptionScope : std::uint8_t { kCells, kMetres };

struct OptionSpec {
  const char* name;
  OptionType type;
  OptionScope scope;
  bool node_parameter;     // read by the planner and cloud bridge nodes as ~name
  double default_value;    // as a number: bools 0/1, the algorithm its index
  // Accepted values: finite numbers in [min, max] (min excluded when min_open), integers for kInt, an
  // index of kAlgorithmNames for kAlgorithm; a bool is always valid.
  double min;
  double max;
  bool min_open;
  const char* unit;        // "" when none
  const char* meaning;
  // kMetres: the cell option it becomes and how: value / resolution (-1) or value * resolution (1).
  const char* in_cells;
  int resolution_power;
  double (*get)(const PlannerParameters&);
  void (*set)(PlannerParameters&, double);
};

// Every option, plan options first, in the order the planner checks them.
const std::vector<OptionSpec>& optionsTable();
// The row of `name`, or nullptr.
const OptionSpec* findOption(const std::string& name);

// "" when `value` is acceptable for `spec`, else "<name> must be <rule>, got <value>".
std::string optionProblem(const OptionSpec& spec, double value);
// The same wording for a value that is not even a number (a wrapper's caller passed text, say): `got` as
// the caller should see it.
std::string optionProblem(const OptionSpec& spec, const std::string& got);
// The rule of `spec` as the problem states it, e.g. "an integer in 1..101", "a finite number > 0".
std::string optionRule(const OptionSpec& spec);
// The first problem of a plan's options (kCells rows, then the one rule between two of them: jps needs
// cost_factor 0), "" when there is none. plan() refuses such a
// request with INVALID_REQUEST.
std::string optionsProblem(const PlannerOptions& options);
// The first problem of a node's configuration (the rows that are node parameters), "" when none.
std::string parametersProblem(const PlannerParameters& parameters);

const char* algorithmName(Algorithm algorithm);
// "" and *out set when `name` is an algorithm's name, else the problem ("algorithm must be one of ...").
std::string algorithmOf(const std::string& name, Algorithm* out);

// `options` with the cell options of `inflation` at `resolution` (m per cell): robot and inflation radius
// divided by it, the decay per metre multiplied by it. "" on success; the problem, and *options left
// alone, when the resolution is not a finite number > 0.
std::string optionsInCells(double resolution, const InflationParams& inflation, PlannerOptions* options);

}  // namespace offload_planner
