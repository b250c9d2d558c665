// dynamic_reconfigure of the planner node without a master: cfg/Planner.cfg's parameters are rows of the core's
// options table (same defaults), a value the table refuses is refused with the options in force kept, and options
// set on a running handler reach its next plan (the map in force inflated again).
#include <gtest/gtest.h>

#include <cmath>
#include <limits>

#include "offload_planner_cpp/planner_reconfigure.h"
#include "offload_planner_cpp/planner_ros.h"

using namespace offload_planner;
using offload_msgs::PlanPath;
using offload_planner_cpp::PlannerConfig;

namespace {

// 10 x 6 cells at 0.5 m, origin (0, 0); a wall at x = 4 for y = 0..4.
nav_msgs::OccupancyGrid::Ptr wallMap() {
  nav_msgs::OccupancyGrid::Ptr map(new nav_msgs::OccupancyGrid);
  map->header.frame_id = "map";
  map->info.resolution = 0.5f;
  map->info.width = 10;
  map->info.height = 6;
  map->info.origin.orientation.w = 1.0;
  map->data.assign(60, 0);
  for (int y = 0; y < 5; ++y) map->data[y * 10 + 4] = 100;
  return map;
}

// From the centre of cell (3, 0), one cell from the wall, to cell (0, 0).
PlanPath::Request besideTheWall() {
  PlanPath::Request req;
  req.start.header.frame_id = req.goal.header.frame_id = "map";
  req.start.pose.position.x = 1.75;
  req.start.pose.position.y = 0.25;
  req.goal.pose.position.x = 0.25;
  req.goal.pose.position.y = 0.25;
  req.goal.pose.orientation.w = 1.0;
  return req;
}

}  // namespace

TEST(PlannerReconfigure, EveryCfgParameterIsATableRowWithTheTablesDefault) {
  const PlannerConfig defaults = PlannerConfig::__getDefault__();
  PlannerParameters from_cfg;
  from_cfg.inflation.robot_radius_m = 7.0;   // overwritten by the .cfg's default if it names robot_radius
  ASSERT_EQ(parametersFromConfig(defaults, &from_cfg), "");
  const PlannerParameters table;   // the structs' initialisers are the table's defaults
  int rows = 0;
  for (const auto& param : PlannerConfig::__getParamDescriptions__()) {
    const OptionSpec* spec = findOption(param->name);
    ASSERT_NE(spec, nullptr) << param->name;
    EXPECT_TRUE(spec->node_parameter) << param->name;
    EXPECT_EQ(spec->get(from_cfg), spec->get(table)) << param->name << ": the .cfg's default is not the table's";
    ++rows;
  }
  EXPECT_EQ(rows, 6);   // algorithm, any_angle, cost_factor, robot_radius, inflation_radius, cost_scaling_factor
}

TEST(PlannerReconfigure, ValuesRoundTripThroughTheConfig) {
  PlannerParameters set;
  set.options.algorithm = Algorithm::kAStar;
  set.options.any_angle = true;
  set.options.cost_factor = 3.0;
  set.inflation.robot_radius_m = 0.2;
  set.inflation.inflation_radius_m = 0.55;
  set.inflation.cost_scaling_factor = 4.0;
  PlannerConfig config = PlannerConfig::__getDefault__();
  configFromParameters(set, &config);
  EXPECT_EQ(config.algorithm, "astar");
  EXPECT_TRUE(config.any_angle);
  EXPECT_EQ(config.inflation_radius, 0.55);
  PlannerParameters read;
  ASSERT_EQ(parametersFromConfig(config, &read), "");
  for (const OptionSpec& spec : optionsTable()) EXPECT_EQ(spec.get(read), spec.get(set)) << spec.name;
  EXPECT_EQ(changedParameters(PlannerParameters(), read),
            "algorithm astar, any_angle true, cost_factor 3, robot_radius 0.20000000000000001, inflation_radius "
            "0.55000000000000004, cost_scaling_factor 4");
  EXPECT_EQ(changedParameters(read, read), "");
}

TEST(PlannerReconfigure, RefusesWhatTheTableRefusesAndKeepsTheParameters) {
  PlannerParameters in_force;
  in_force.inflation.inflation_radius_m = 0.3;
  in_force.options.algorithm = Algorithm::kDijkstra;   // not the default: a refused edit must not reset it
  const auto refused = [&](void (*edit)(PlannerConfig*)) {
    PlannerConfig config = PlannerConfig::__getDefault__();
    configFromParameters(in_force, &config);
    edit(&config);
    PlannerParameters parameters = in_force;
    const std::string problem = parametersFromConfig(config, &parameters);
    EXPECT_EQ(parameters.inflation.inflation_radius_m, 0.3) << "changed although refused: " << problem;
    EXPECT_EQ(parameters.options.algorithm, Algorithm::kDijkstra);
    return problem;
  };
  EXPECT_EQ(refused([](PlannerConfig* c) { c->inflation_radius = -1.0; }),
            "inflation_radius must be a finite number >= 0, got -1");
  EXPECT_EQ(refused([](PlannerConfig* c) { c->cost_factor = std::numeric_limits<double>::quiet_NaN(); }),
            "cost_factor must be a finite number >= 0, got nan");
  EXPECT_EQ(refused([](PlannerConfig* c) { c->algorithm = "bfs"; }),
            "algorithm must be one of dijkstra, astar, jps, auto, got \"bfs\"");
  // Each value alone is fine; the table's rule between two of them is not.
  EXPECT_EQ(refused([](PlannerConfig* c) { c->algorithm = "jps"; c->cost_factor = 2.0; c->inflation_radius = 1; }),
            "algorithm jps is exact only where every passable cell costs the same: cost_factor must be 0, got 2");
}

TEST(PlannerReconfigure, NewParametersReachTheNextPlanOnTheMapInForce) {
  PlanRequestHandler handler;
  ASSERT_TRUE(handler.setMap(wallMap(), nullptr));
  PlanPath::Response res;
  handler.handle(besideTheWall(), &res);
  ASSERT_EQ(res.status, PlanPath::Response::OK) << res.message;

  PlannerParameters wide;
  wide.inflation.robot_radius_m = 0.6;   // 1.2 cells: the start, one cell from the wall, is inside it
  handler.setParameters(wide);
  handler.handle(besideTheWall(), &res);
  EXPECT_EQ(res.status, PlanPath::Response::START_BLOCKED) << "the map in force was not inflated again";

  PlannerParameters astar = wide;   // no new inflation: the inflated grid is kept
  astar.options.algorithm = Algorithm::kAStar;
  handler.setParameters(astar);
  handler.handle(besideTheWall(), &res);
  EXPECT_EQ(res.status, PlanPath::Response::START_BLOCKED);

  handler.setParameters(PlannerParameters());
  handler.handle(besideTheWall(), &res);
  EXPECT_EQ(res.status, PlanPath::Response::OK) << "inflation off again: the raw map";
  EXPECT_NEAR(res.cost_m, 1.5, 1e-9);

  handler.setParameters(wide);   // and a map arriving later is inflated with the parameters in force
  ASSERT_TRUE(handler.setMap(wallMap(), nullptr));
  handler.handle(besideTheWall(), &res);
  EXPECT_EQ(res.status, PlanPath::Response::START_BLOCKED);
}

TEST(PlannerReconfigure, ParametersWithoutAMapApplyToTheFirstMap) {
  PlanRequestHandler handler;
  PlannerParameters wide;
  wide.inflation.robot_radius_m = 0.6;
  handler.setParameters(wide);
  PlanPath::Response res;
  handler.handle(besideTheWall(), &res);
  EXPECT_EQ(res.status, PlanPath::Response::NO_MAP);
  ASSERT_TRUE(handler.setMap(wallMap(), nullptr));
  handler.handle(besideTheWall(), &res);
  EXPECT_EQ(res.status, PlanPath::Response::START_BLOCKED);
}

int main(int argc, char** argv) {
  ros::Time::init();  // path stamps use ros::Time::now(); no master needed
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
