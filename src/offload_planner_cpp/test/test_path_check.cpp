// checkPath (path_check.h): the planner's own paths pass with their length; each lie is named in checkPath's order.
#include <gtest/gtest.h>

#include <cmath>
#include <vector>

#include "dijkstra_grid.h"
#include "offload_planner_cpp/path_check.h"

using namespace offload_planner;
using test::Grid;
using test::kSqrt2;

namespace {

PathCheck checkOf(Grid& g, const std::vector<Cell>& path, bool any_angle = false, Cell start = {-1, -1},
                  Cell end = {-1, -1}) {
  if (start.x < 0) start = path.front();
  if (end.x < 0) end = path.back();
  return checkPath(g.data.data(), g.width, g.height, path.data(), path.size(), start, end, any_angle,
                   PlannerOptions());
}

}  // namespace

TEST(PathCheck, PlannedPathsPassWithTheirCost) {
  Grid g({"......", "..##..", "......", "......"});
  for (bool any_angle : {false, true}) {
    PlannerOptions o;
    o.any_angle = any_angle;
    const PlanResult r = g.plan({0, 0}, {5, 3}, o);
    ASSERT_TRUE(r.ok());
    const PathCheck c = checkOf(g, r.path, any_angle);
    EXPECT_EQ(c.problem, PathProblem::kNone) << any_angle;
    EXPECT_NEAR(c.length_cells, r.cost, 1e-9) << any_angle;
  }
  const PathCheck one = checkOf(g, {{4, 2}});
  EXPECT_EQ(one.problem, PathProblem::kNone);
  EXPECT_EQ(one.length_cells, 0.0);
  EXPECT_NEAR(checkOf(g, {{0, 2}, {1, 3}, {2, 3}}).length_cells, 1 + kSqrt2, 1e-12);
}

TEST(PathCheck, EachLieIsNamed) {
  Grid g({"......", "..##..", "......", "......"});
  EXPECT_EQ(checkOf(g, {{0, 0}, {-1, 0}}).problem, PathProblem::kLeavesMap);
  EXPECT_EQ(checkOf(g, {{0, 0}, {1, 4}}, true).problem, PathProblem::kLeavesMap);
  EXPECT_EQ(checkOf(g, {{0, 0}, {1, 0}}, false, {1, 1}).problem, PathProblem::kWrongStart);
  EXPECT_EQ(checkOf(g, {{0, 0}, {1, 0}}, false, {0, 0}, {2, 0}).problem, PathProblem::kWrongEnd);
  EXPECT_EQ(checkOf(g, {{0, 0}, {2, 1}}).problem, PathProblem::kNotEightConnected);
  EXPECT_EQ(checkOf(g, {{0, 0}, {1, 0}, {1, 0}, {2, 0}}).problem, PathProblem::kNotEightConnected);
  EXPECT_EQ(checkOf(g, {{0, 0}, {3, 0}, {3, 0}}, true).problem, PathProblem::kRepeatsCorner);
  const PathCheck wall = checkOf(g, {{0, 0}, {1, 0}, {2, 1}, {3, 2}});   // enters the blocked (2, 1)
  EXPECT_EQ(wall.problem, PathProblem::kBlocked);
  EXPECT_EQ(wall.index, 1u);
  EXPECT_EQ(checkOf(g, {{1, 0}, {2, 1}}).problem, PathProblem::kBlocked);
  EXPECT_EQ(checkOf(g, {{1, 2}, {2, 1}}).problem, PathProblem::kBlocked);
  EXPECT_EQ(checkOf(g, {{1, 0}, {1, 1}, {2, 2}}).problem, PathProblem::kBlocked);   // cuts the corner of (2, 1)
  EXPECT_EQ(checkOf(g, {{2, 1}}).problem, PathProblem::kBlocked);                    // one blocked cell
  EXPECT_EQ(checkOf(g, {{0, 0}, {5, 3}}, true).problem, PathProblem::kBlocked);      // a line through the wall
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
