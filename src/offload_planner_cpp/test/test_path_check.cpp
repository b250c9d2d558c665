// checkPath (path_check.h): the planner's own paths pass with their length; each lie is named in checkPath's order.
#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <string>
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

// The 8-connected check takes each unit move's end cell and its corner cells directly: on random grids (blocked, unknown
// and costed cells) and random walks it says what the segment walk of every move says, and names the same move.
TEST(PathCheck, UnitMovesAgreeWithTheSegmentWalk) {
  std::mt19937 rng(7);
  const int dirs[8][2] = {{1, 0}, {1, 1}, {0, 1}, {-1, 1}, {-1, 0}, {-1, -1}, {0, -1}, {1, -1}};
  std::size_t blocked = 0;
  for (int trial = 0; trial < 3000; ++trial) {
    std::vector<std::string> rows(9, std::string(12, '.'));
    for (auto& row : rows) {
      for (char& c : row) c = "..........##?7"[rng() % 14];
    }
    Grid g(rows);
    std::vector<Cell> path{{static_cast<int>(rng() % 12), static_cast<int>(rng() % 9)}};
    const std::size_t steps = rng() % 12;
    while (path.size() <= steps) {
      const int* d = dirs[rng() % 8];
      const Cell next{path.back().x + d[0], path.back().y + d[1]};
      if (next.x >= 0 && next.y >= 0 && next.x < 12 && next.y < 9) path.push_back(next);
    }
    std::size_t first_blocked = path.size();
    for (std::size_t k = 0; k < (path.size() > 1 ? path.size() - 1 : 1); ++k) {
      if (!segmentClear(g.data.data(), 12, 9, path[k], path[path.size() > 1 ? k + 1 : k], PlannerOptions())) {
        first_blocked = k;
        break;
      }
    }
    const PathCheck c = checkOf(g, path);
    if (first_blocked == path.size()) {
      EXPECT_EQ(c.problem, PathProblem::kNone) << trial;
    } else {
      ++blocked;
      EXPECT_EQ(c.problem, PathProblem::kBlocked) << trial;
      EXPECT_EQ(c.index, first_blocked) << trial;
    }
  }
  EXPECT_GT(blocked, 1000u);   // both verdicts met often
  EXPECT_LT(blocked, 2900u);
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
