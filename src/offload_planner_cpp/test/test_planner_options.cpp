// The planner options table (planner_options.h) against a copy written out by hand: every name, type,
// default, bound and conversion, the one wording of its problems, the algorithm names, and plan() refusing
// exactly what the table refuses.
#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <string>
#include <vector>

#include "offload_planner_cpp/dijkstra.h"
#include "offload_planner_cpp/planner_options.h"

using namespace offload_planner;

namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

struct Expected {
  std::string name;
  OptionType type;
  OptionScope scope;
  bool node_parameter;
  double default_value;
  double min;
  double max;
  bool min_open;
  std::string unit;
  std::string in_cells;
  int resolution_power;
};

// The contract, written independently of the table: a changed name, default or bound fails here.
const std::vector<Expected>& expectedTable() {
  using T = OptionType;
  const auto C = OptionScope::kCells;
  const auto M = OptionScope::kMetres;
  static const std::vector<Expected> table = {
      {"lethal_threshold", T::kInt, C, true, 50, 1, 101, false, "occupancy", "", 0},
      {"unknown_is_obstacle", T::kBool, C, true, 1, 0, 1, false, "", "", 0},
      {"goal_tolerance_cells", T::kReal, C, false, 0, 0, kInf, false, "cells", "", 0},
      {"stop_at_goal", T::kBool, C, false, 1, 0, 1, false, "", "", 0},
      {"cost_factor", T::kReal, C, true, 0, 0, kInf, false, "", "", 0},
      {"neutral_cost", T::kReal, C, true, 50, 0, kInf, true, "", "", 0},
      {"robot_radius_cells", T::kReal, C, false, 0, 0, 10000, false, "cells", "", 0},
      {"inflation_radius_cells", T::kReal, C, false, 0, 0, 10000, false, "cells", "", 0},
      {"inflation_decay", T::kReal, C, false, 0.5, 0, kInf, false, "1/cell", "", 0},
      {"algorithm", T::kAlgorithm, C, true, 3, 0, 3, false, "", "", 0},   // auto
      {"any_angle", T::kBool, C, true, 0, 0, 1, false, "", "", 0},
      {"robot_radius", T::kReal, M, true, 0, 0, kInf, false, "m", "robot_radius_cells", -1},
      {"inflation_radius", T::kReal, M, true, 0, 0, kInf, false, "m", "inflation_radius_cells", -1},
      {"cost_scaling_factor", T::kReal, M, true, 10, 0, kInf, false, "1/m", "inflation_decay", 1},
  };
  return table;
}

PlanResult planWith(const PlannerOptions& options) {
  std::vector<std::int8_t> grid(16, 0);
  DijkstraPlanner planner;
  return planner.plan(grid.data(), grid.size(), 4, 4, Cell{0, 0}, Cell{3, 3}, options);
}

}  // namespace

TEST(PlannerOptionsTable, HoldsEveryOptionWithItsDefaultAndBounds) {
  const auto& table = optionsTable();
  const auto& expected = expectedTable();
  ASSERT_EQ(table.size(), expected.size());
  for (std::size_t k = 0; k < table.size(); ++k) {
    const OptionSpec& got = table[k];
    const Expected& want = expected[k];
    SCOPED_TRACE(want.name);
    EXPECT_EQ(got.name, want.name);
    EXPECT_EQ(got.type, want.type);
    EXPECT_EQ(got.scope, want.scope);
    EXPECT_EQ(got.node_parameter, want.node_parameter);
    EXPECT_EQ(got.default_value, want.default_value);
    EXPECT_EQ(got.min, want.min);
    EXPECT_EQ(got.max, want.max);
    EXPECT_EQ(got.min_open, want.min_open);
    EXPECT_EQ(got.unit, want.unit);
    EXPECT_EQ(got.in_cells ? std::string(got.in_cells) : std::string(), want.in_cells);
    EXPECT_EQ(got.resolution_power, want.resolution_power);
    EXPECT_FALSE(std::string(got.meaning).empty());
    EXPECT_EQ(findOption(want.name), &got);
  }
  EXPECT_EQ(findOption("no_such_option"), nullptr);
}

TEST(PlannerOptionsTable, DefaultsAreTheStructsAndAreAccepted) {
  const PlannerParameters defaults;
  for (const OptionSpec& spec : optionsTable()) {
    SCOPED_TRACE(spec.name);
    EXPECT_EQ(spec.get(defaults), spec.default_value);
    EXPECT_EQ(optionProblem(spec, spec.default_value), "");
  }
  EXPECT_EQ(optionsProblem(PlannerOptions()), "");
  EXPECT_EQ(parametersProblem(defaults), "");
}

TEST(PlannerOptionsTable, EachRowReadsAndWritesItsOwnField) {
  for (const OptionSpec& spec : optionsTable()) {
    SCOPED_TRACE(spec.name);
    PlannerParameters p;
    const double other = spec.type == OptionType::kBool        ? 1.0 - spec.default_value
                         : spec.type == OptionType::kAlgorithm ? (spec.default_value == 0.0 ? 1.0 : 0.0)
                                                               : spec.default_value + 1.0;
    spec.set(p, other);
    EXPECT_EQ(spec.get(p), other);
    for (const OptionSpec& rest : optionsTable()) {   // nothing else moved
      if (&rest != &spec) EXPECT_EQ(rest.get(p), rest.default_value) << rest.name;
    }
  }
}

TEST(PlannerOptionsTable, EveryBoundIsCheckedWithOneWording) {
  for (const OptionSpec& spec : optionsTable()) {
    SCOPED_TRACE(spec.name);
    if (spec.type == OptionType::kBool) {
      EXPECT_EQ(optionProblem(spec, 0.0), "");
      EXPECT_EQ(optionProblem(spec, 1.0), "");
      continue;
    }
    const std::string prefix = std::string(spec.name) + " must be " + optionRule(spec) + ", got ";
    EXPECT_EQ(optionProblem(spec, spec.min), spec.min_open ? prefix + "0" : "");
    EXPECT_EQ(optionProblem(spec, spec.min - 1.0), prefix + std::to_string(static_cast<int>(spec.min) - 1));
    EXPECT_NE(optionProblem(spec, kNaN), "");
    EXPECT_NE(optionProblem(spec, kInf), "");
    if (std::isfinite(spec.max)) {
      EXPECT_EQ(optionProblem(spec, spec.max), "");
      EXPECT_EQ(optionProblem(spec, spec.max + 1.0).rfind(prefix, 0), 0u);
    } else {
      EXPECT_EQ(optionProblem(spec, 1e300), "");
    }
    if (spec.type != OptionType::kReal) EXPECT_NE(optionProblem(spec, spec.min + 0.5), "");
  }
  EXPECT_EQ(optionProblem(*findOption("lethal_threshold"), 0), "lethal_threshold must be an integer in 1..101, got 0");
  EXPECT_EQ(optionProblem(*findOption("neutral_cost"), 0), "neutral_cost must be a finite number > 0, got 0");
  EXPECT_EQ(optionProblem(*findOption("cost_factor"), kNaN), "cost_factor must be a finite number >= 0, got nan");
  EXPECT_EQ(optionProblem(*findOption("robot_radius_cells"), 10000.5),
            "robot_radius_cells must be a finite number in 0..10000, got 10000.5");
  EXPECT_EQ(optionProblem(*findOption("algorithm"), 4), "algorithm must be one of dijkstra, astar, jps, auto, got 4");
}

TEST(PlannerOptionsTable, AlgorithmNamesAreTheEnumsInOrder) {
  ASSERT_EQ(kAlgorithmCount, 4);
  EXPECT_STREQ(kAlgorithmNames[0], "dijkstra");
  EXPECT_STREQ(kAlgorithmNames[1], "astar");
  EXPECT_STREQ(kAlgorithmNames[2], "jps");
  EXPECT_STREQ(kAlgorithmNames[3], "auto");
  for (Algorithm a : {Algorithm::kDijkstra, Algorithm::kAStar, Algorithm::kJps, Algorithm::kAuto}) {
    Algorithm back = a == Algorithm::kDijkstra ? Algorithm::kAStar : Algorithm::kDijkstra;
    EXPECT_EQ(algorithmOf(algorithmName(a), &back), "");
    EXPECT_EQ(back, a);
  }
  Algorithm untouched = Algorithm::kAStar;
  EXPECT_EQ(algorithmOf("bfs", &untouched), "algorithm must be one of dijkstra, astar, jps, auto, got \"bfs\"");
  EXPECT_EQ(algorithmOf("Dijkstra", &untouched).empty(), false) << "names are case sensitive";
  EXPECT_EQ(untouched, Algorithm::kAStar);
}

TEST(PlannerOptionsTable, PlanRefusesWhatTheTableRefusesWithItsMessage) {
  PlannerOptions bad;
  bad.lethal_threshold = 102;
  PlanResult r = planWith(bad);
  EXPECT_EQ(r.status, PlanStatus::kInvalidRequest);
  EXPECT_EQ(r.message, "lethal_threshold must be an integer in 1..101, got 102");
  bad = PlannerOptions();
  bad.goal_tolerance_cells = -2.0;
  EXPECT_EQ(planWith(bad).message, "goal_tolerance_cells must be a finite number >= 0, got -2");
  bad = PlannerOptions();
  bad.inflation_decay = -kInf;
  EXPECT_EQ(planWith(bad).message, "inflation_decay must be a finite number >= 0, got -inf");
  bad = PlannerOptions();
  bad.algorithm = static_cast<Algorithm>(7);
  EXPECT_EQ(planWith(bad).message, "algorithm must be one of dijkstra, astar, jps, auto, got 7");
  // The first problem in table order.
  bad = PlannerOptions();
  bad.neutral_cost = 0.0;
  bad.robot_radius_cells = -1.0;
  EXPECT_EQ(planWith(bad).message, "neutral_cost must be a finite number > 0, got 0");
  // The bounds themselves are accepted.
  PlannerOptions edge;
  edge.lethal_threshold = 101;
  edge.robot_radius_cells = 0.0;
  edge.inflation_radius_cells = 3.0;
  edge.inflation_decay = 0.0;
  edge.algorithm = Algorithm::kAStar;
  EXPECT_EQ(planWith(edge).status, PlanStatus::kOk) << planWith(edge).message;
}

TEST(PlannerOptionsTable, JumpPointSearchIsRefusedWhereCellsCostDifferently) {
  PlannerOptions jps;
  jps.algorithm = Algorithm::kJps;
  EXPECT_EQ(planWith(jps).status, PlanStatus::kOk) << planWith(jps).message;
  jps.cost_factor = 3.0;
  const std::string why =
      "algorithm jps is exact only where every passable cell costs the same: cost_factor must be 0, got 3";
  EXPECT_EQ(optionsProblem(jps), why);
  EXPECT_EQ(planWith(jps).status, PlanStatus::kInvalidRequest);
  EXPECT_EQ(planWith(jps).message, why);
  PlannerParameters node;
  node.options = jps;
  EXPECT_EQ(parametersProblem(node), why);
  // auto chooses per plan, so it takes any cost model.
  jps.algorithm = Algorithm::kAuto;
  EXPECT_EQ(planWith(jps).status, PlanStatus::kOk) << planWith(jps).message;
}

TEST(PlannerOptionsTable, NodeParametersAreCheckedInMetresWithoutTheCellBound) {
  PlannerParameters p;
  p.inflation.robot_radius_m = 1000.0;   // 20000 cells at 5 cm: the node takes it, the cells are per map
  EXPECT_EQ(parametersProblem(p), "");
  p.inflation.robot_radius_m = -0.1;
  EXPECT_EQ(parametersProblem(p), "robot_radius must be a finite number >= 0, got -0.1");
  p = PlannerParameters();
  p.inflation.cost_scaling_factor = kNaN;
  EXPECT_EQ(parametersProblem(p), "cost_scaling_factor must be a finite number >= 0, got nan");
  p = PlannerParameters();
  p.options.lethal_threshold = 0;
  EXPECT_EQ(parametersProblem(p), "lethal_threshold must be an integer in 1..101, got 0");
  // Per-request options are not node parameters.
  p = PlannerParameters();
  p.options.goal_tolerance_cells = -1.0;
  EXPECT_EQ(parametersProblem(p), "");
}

TEST(PlannerOptionsTable, MetresBecomeCellsWithTheMapsResolution) {
  PlannerOptions options;
  options.cost_factor = 3.0;
  InflationParams metres;
  metres.robot_radius_m = 0.22;
  metres.inflation_radius_m = 0.55;
  metres.cost_scaling_factor = 10.0;
  ASSERT_EQ(optionsInCells(0.05, metres, &options), "");
  EXPECT_EQ(options.robot_radius_cells, 0.22 / 0.05);
  EXPECT_EQ(options.inflation_radius_cells, 0.55 / 0.05);
  EXPECT_EQ(options.inflation_decay, 10.0 * 0.05);
  EXPECT_EQ(options.cost_factor, 3.0) << "other options untouched";
  EXPECT_DOUBLE_EQ(InflationParams().cost_scaling_factor * 0.05, PlannerOptions().inflation_decay)
      << "costmap_2d's default decay at 5 cm cells is the core's default per cell";
  PlannerOptions kept = options;
  for (double resolution : {0.0, -0.05, kNaN, kInf}) {
    EXPECT_EQ(optionsInCells(resolution, metres, &kept).rfind("resolution must be a finite number > 0, got ", 0), 0u);
    EXPECT_EQ(kept.robot_radius_cells, options.robot_radius_cells);
  }
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
