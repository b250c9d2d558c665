// Core planner on small hand-made grids, every error, and agreement with a textbook binary-heap
// Dijkstra on random grids.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <queue>
#include <random>
#include <string>
#include <vector>

#include "dijkstra_grid.h"

using namespace offload_planner;

using test::DijkstraOptions;
using test::Grid;
using test::expectValidPath;
using test::kSqrt2;
using test::referenceCost;

TEST(Dijkstra, StraightAndDiagonalCosts) {
  Grid g({".....", ".....", "....."});
  auto r = g.plan({0, 0}, {4, 0});
  expectValidPath(g, r, {0, 0}, {4, 0});
  EXPECT_DOUBLE_EQ(r.cost, 4.0);
  r = g.plan({0, 0}, {2, 2});
  expectValidPath(g, r, {0, 0}, {2, 2});
  EXPECT_DOUBLE_EQ(r.cost, 2 * kSqrt2);
  r = g.plan({0, 0}, {4, 2});
  EXPECT_NEAR(r.cost, 2 + 2 * kSqrt2, 1e-12);
  EXPECT_GT(r.expansions, 0u);
  EXPECT_GE(r.seconds, 0.0);
}

TEST(Dijkstra, StartEqualsGoal) {
  Grid g({"...", "..."});
  auto r = g.plan({1, 1}, {1, 1});
  ASSERT_TRUE(r.ok());
  ASSERT_EQ(r.path.size(), 1u);
  EXPECT_EQ(r.cost, 0.0);
  EXPECT_EQ(r.expansions, 1u) << "the goal is the start: nothing else to settle";
}

TEST(Dijkstra, NoCornerCutting) {
  // The only diagonal gap squeezes between two obstacles; the path must go around.
  Grid g({".#.",
          "#..",
          "..."});
  auto r = g.plan({0, 0}, {1, 1});
  EXPECT_EQ(r.status, PlanStatus::kNoPath) << "moved diagonally between two blocked corners";
  Grid h({"..#",
          ".#.",
          "..."});
  // (1, 0) -> (2, 1) would squeeze between (2, 0) and (1, 1): the way round is 6 straight steps.
  r = h.plan({1, 0}, {2, 1});
  expectValidPath(h, r, {1, 0}, {2, 1});
  EXPECT_NEAR(r.cost, 6.0, 1e-12);
  r = h.plan({0, 0}, {2, 2});
  expectValidPath(h, r, {0, 0}, {2, 2});
  EXPECT_NEAR(r.cost, 4.0, 1e-12);  // down then right: no diagonal past the centre obstacle
}

TEST(Dijkstra, UnknownCellsAndLethalThreshold) {
  Grid g({"..?..", "###?#", "....."});
  EXPECT_EQ(g.plan({0, 0}, {0, 2}).status, PlanStatus::kNoPath);
  DijkstraOptions unknown_free;
  unknown_free.unknown_is_obstacle = false;
  auto r = g.plan({0, 0}, {0, 2}, unknown_free);
  ASSERT_TRUE(r.ok());
  EXPECT_NE(std::find(r.path.begin(), r.path.end(), Cell{3, 1}), r.path.end()) << "through the unknown gap";

  Grid c({"...", "555", "..."});  // occupancy 50 across the middle
  EXPECT_EQ(c.plan({0, 0}, {0, 2}).status, PlanStatus::kNoPath);
  DijkstraOptions high;
  high.lethal_threshold = 51;
  EXPECT_TRUE(c.plan({0, 0}, {0, 2}, high).ok());

  Grid walls({"...", "###", "..."});  // occupancy 100: lethal only below the documented maximum 101
  EXPECT_EQ(walls.plan({0, 0}, {0, 2}).status, PlanStatus::kNoPath);
  DijkstraOptions nothing_lethal;
  nothing_lethal.lethal_threshold = 101;
  const auto through = walls.plan({0, 0}, {0, 2}, nothing_lethal);
  ASSERT_TRUE(through.ok()) << through.message;
  EXPECT_NEAR(through.cost, 2.0, 1e-12);
}

TEST(Dijkstra, GoalToleranceFindsNearestFreeCell) {
  Grid g({".....",
          "...##",
          "...##"});
  DijkstraOptions o;
  EXPECT_EQ(g.plan({0, 0}, {4, 2}, o).status, PlanStatus::kGoalBlocked);
  o.goal_tolerance_cells = 1.5;  // all three neighbours are blocked
  EXPECT_EQ(g.plan({0, 0}, {4, 2}, o).status, PlanStatus::kGoalBlocked);
  o.goal_tolerance_cells = 2.0;  // (2, 2) and (4, 0) are both 2 away; ties go to the first in row order
  auto r = g.plan({0, 0}, {4, 2}, o);
  ASSERT_TRUE(r.ok()) << r.message;
  EXPECT_EQ(r.goal, (Cell{4, 0}));
  expectValidPath(g, r, {0, 0}, {4, 0});
  EXPECT_DOUBLE_EQ(r.cost, 4.0);
}

TEST(Dijkstra, GoalToleranceSkipsUnreachableCandidates) {
  // The goal sits in a walled pocket; the nearest free cell outside it within tolerance is chosen.
  Grid g({".......",
          ".......",
          "....###",
          "....#..",
          "....#.."});
  DijkstraOptions o;
  EXPECT_EQ(g.plan({0, 0}, {6, 4}, o).status, PlanStatus::kNoPath);
  o.goal_tolerance_cells = 2.5;  // only pocket cells lie within 2.5
  EXPECT_EQ(g.plan({0, 0}, {6, 4}, o).status, PlanStatus::kNoPath);
  o.goal_tolerance_cells = 3.0;  // (6, 1) and (3, 4) are 3 away and reachable; row order picks (6, 1)
  auto r = g.plan({0, 0}, {6, 4}, o);
  ASSERT_TRUE(r.ok()) << r.message;
  EXPECT_EQ(r.goal, (Cell{6, 1}));
  expectValidPath(g, r, {0, 0}, {6, 1});
}

TEST(Dijkstra, HugeToleranceIsClampedToTheMap) {
  Grid g({".....", ".....", ".....", "....#", "...##"});
  DijkstraOptions o;
  for (double tolerance : {1e9, 3e9, 1e18, 1e300}) {
    o.goal_tolerance_cells = tolerance;
    auto r = g.plan({0, 0}, {4, 4}, o);
    ASSERT_TRUE(r.ok()) << tolerance << ": " << r.message;
    EXPECT_EQ(r.goal, (Cell{3, 3})) << tolerance;  // the free diagonal neighbour
  }
  o.goal_tolerance_cells = INFINITY;
  EXPECT_EQ(g.plan({0, 0}, {4, 4}, o).status, PlanStatus::kInvalidRequest);
}

TEST(Dijkstra, ToleranceCostsNothingWhenTheGoalIsReachable) {
  Grid g(std::vector<std::string>(300, std::string(300, '.')));
  DijkstraOptions o;
  const auto plain = g.plan({150, 150}, {152, 151}, o);
  o.goal_tolerance_cells = 1e6;
  const auto tolerant = g.plan({150, 150}, {152, 151}, o);
  ASSERT_TRUE(plain.ok() && tolerant.ok());
  EXPECT_EQ(tolerant.goal, (Cell{152, 151}));
  EXPECT_EQ(tolerant.expansions, plain.expansions);
  EXPECT_LT(plain.expansions, 50u);
}

TEST(Dijkstra, StopAtGoalSettlesFewerCells) {
  Grid g(std::vector<std::string>(50, std::string(50, '.')));
  DijkstraOptions all;
  all.stop_at_goal = false;
  const auto early = g.plan({0, 0}, {3, 0});
  const auto full = g.plan({0, 0}, {3, 0}, all);
  ASSERT_TRUE(early.ok());
  ASSERT_TRUE(full.ok());
  EXPECT_EQ(full.expansions, 2500u);
  EXPECT_LT(early.expansions, 100u);
  EXPECT_DOUBLE_EQ(early.cost, full.cost);
}

TEST(Dijkstra, AMapBeyondTheIndexRangeIsRefusedBeforeAnyAllocationAndSaysWhy) {
  // 1 x 715,827,881 cells are fewer than 2^31, but with the waves' frame of one cell (3 x 715,827,883) they are
  // not: refused with a message that says so, not "more than 2^31 cells". The size check comes before the data
  // is read, so one byte of data suffices.
  std::int8_t cell = 0;
  DijkstraPlanner p;
  const int tall = 715827881;
  const auto r = p.plan(&cell, static_cast<std::size_t>(tall), 1, tall, {0, 0}, {0, 1});
  EXPECT_EQ(r.status, PlanStatus::kInvalidMap);
  EXPECT_NE(r.message.find("1 x 715827881 cells and a frame of one cell"), std::string::npos) << r.message;
}

TEST(Dijkstra, Errors) {
  Grid g({"..#", "...", "..."});
  DijkstraPlanner p;
  auto r = p.plan(g.data.data(), 0, 0, 0, {0, 0}, {1, 1});
  EXPECT_EQ(r.status, PlanStatus::kInvalidMap);
  EXPECT_NE(r.message.find("empty"), std::string::npos);
  r = p.plan(g.data.data(), g.data.size(), 4, 3, {0, 0}, {1, 1});
  EXPECT_EQ(r.status, PlanStatus::kInvalidMap);
  EXPECT_NE(r.message.find("12 cells but 9"), std::string::npos) << r.message;
  r = g.plan({-1, 0}, {1, 1});
  EXPECT_EQ(r.status, PlanStatus::kStartOffMap);
  EXPECT_NE(r.message.find("(-1, 0)"), std::string::npos);
  r = g.plan({0, 0}, {3, 0});
  EXPECT_EQ(r.status, PlanStatus::kGoalOffMap);
  r = g.plan({0, 0}, {0, 3});
  EXPECT_EQ(r.status, PlanStatus::kGoalOffMap);
  r = g.plan({2, 0}, {0, 0});
  EXPECT_EQ(r.status, PlanStatus::kStartBlocked);
  r = g.plan({0, 0}, {2, 0});
  EXPECT_EQ(r.status, PlanStatus::kGoalBlocked);
  EXPECT_NE(r.message.find("obstacle"), std::string::npos);
  DijkstraOptions bad;
  bad.lethal_threshold = 0;
  EXPECT_EQ(g.plan({0, 0}, {1, 1}, bad).status, PlanStatus::kInvalidRequest);
  bad = DijkstraOptions();
  bad.goal_tolerance_cells = -1;
  EXPECT_EQ(g.plan({0, 0}, {1, 1}, bad).status, PlanStatus::kInvalidRequest);
  bad.goal_tolerance_cells = NAN;
  EXPECT_EQ(g.plan({0, 0}, {1, 1}, bad).status, PlanStatus::kInvalidRequest);
  Grid walled({".#.", ".#.", ".#."});
  r = walled.plan({0, 0}, {2, 2});
  EXPECT_EQ(r.status, PlanStatus::kNoPath);
  EXPECT_NE(r.message.find("unreachable"), std::string::npos);
  EXPECT_TRUE(r.path.empty());
  for (auto s : {PlanStatus::kOk, PlanStatus::kInvalidMap, PlanStatus::kInvalidMap, PlanStatus::kStartOffMap,
                 PlanStatus::kGoalOffMap, PlanStatus::kStartBlocked, PlanStatus::kGoalBlocked, PlanStatus::kNoPath,
                 PlanStatus::kInvalidRequest}) {
    EXPECT_STRNE(statusName(s), "unknown");
  }
}

TEST(Dijkstra, AgreesWithReferenceOnRandomGridsAndReusesBuffers) {
  std::mt19937 rng(7);
  DijkstraPlanner planner;  // one planner across sizes: buffers grow, shrink and get reused
  int checked = 0;
  for (int trial = 0; trial < 60; ++trial) {
    const int w = 5 + static_cast<int>(rng() % 60), h = 5 + static_cast<int>(rng() % 60);
    std::bernoulli_distribution blocked(0.1 + 0.3 * (trial % 3));
    std::vector<std::int8_t> grid(w * h);
    for (auto& v : grid) v = blocked(rng) ? 100 : 0;
    for (int q = 0; q < 5; ++q) {
      Cell s{static_cast<int>(rng() % w), static_cast<int>(rng() % h)};
      Cell g{static_cast<int>(rng() % w), static_cast<int>(rng() % h)};
      grid[s.y * w + s.x] = 0;
      grid[g.y * w + g.x] = 0;
      const double expected = referenceCost(grid, w, h, s, g);
      const auto r = planner.plan(grid.data(), grid.size(), w, h, s, g, DijkstraOptions());
      if (std::isinf(expected)) {
        EXPECT_EQ(r.status, PlanStatus::kNoPath);
      } else {
        ASSERT_TRUE(r.ok()) << r.message;
        EXPECT_NEAR(r.cost, expected, 1e-9);
        // The path traced back is itself a shortest one: its steps add up to the optimum.
        double length = 0;
        for (std::size_t k = 1; k < r.path.size(); ++k) {
          const bool diagonal = r.path[k].x != r.path[k - 1].x && r.path[k].y != r.path[k - 1].y;
          length += diagonal ? kSqrt2 : 1.0;
        }
        EXPECT_NEAR(length, expected, 1e-9) << "trial " << trial;
        ++checked;
      }
    }
  }
  EXPECT_GT(checked, 100);
}

TEST(Dijkstra, RowsFromAnEarlierMapOfTheSameSizeAreNeverRead) {
  // The waves derive their rows from the grid as they reach them and never reset the rest: a row left over
  // from an earlier map (same size, other walls) must never be read. Tall and narrow maps, so the waves
  // derive many row blocks and meet far from both ends; every map is new and the planner is the same.
  std::mt19937 rng(23);
  DijkstraPlanner planner;
  int checked = 0;
  for (int trial = 0; trial < 40; ++trial) {
    const int w = 3 + static_cast<int>(rng() % 12);
    const int h = 150 + static_cast<int>(rng() % 100);
    std::bernoulli_distribution blocked(trial % 4 == 0 ? 0.0 : 0.05 + 0.1 * (trial % 3));
    std::vector<std::int8_t> grid(static_cast<std::size_t>(w) * h);
    for (auto& v : grid) v = blocked(rng) ? 100 : 0;
    // Start and goal anywhere: near the ends, in the middle, or close together.
    Cell s{static_cast<int>(rng() % w), static_cast<int>(rng() % h)};
    Cell g{static_cast<int>(rng() % w), trial % 2 ? static_cast<int>(rng() % h) : h - 1 - s.y};
    grid[s.y * w + s.x] = 0;
    grid[g.y * w + g.x] = 0;
    const double expected = referenceCost(grid, w, h, s, g);
    for (const bool stop_at_goal : {true, false}) {
      DijkstraOptions o;
      o.stop_at_goal = stop_at_goal;
      const auto r = planner.plan(grid.data(), grid.size(), w, h, s, g, o);
      if (std::isinf(expected)) {
        EXPECT_EQ(r.status, PlanStatus::kNoPath) << "trial " << trial;
        continue;
      }
      ASSERT_TRUE(r.ok()) << r.message << " trial " << trial;
      EXPECT_NEAR(r.cost, expected, 1e-9) << "trial " << trial;
      for (std::size_t k = 1; k < r.path.size(); ++k) {
        const Cell a = r.path[k - 1], b = r.path[k];
        ASSERT_LE(std::max(std::abs(a.x - b.x), std::abs(a.y - b.y)), 1);
        ASSERT_EQ(grid[b.y * w + b.x], 0) << "the path enters a wall of this map, trial " << trial;
      }
      ++checked;
    }
  }
  EXPECT_GT(checked, 40);
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
