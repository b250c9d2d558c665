// Jump point search and the automatic choice (algorithm jps and auto) against a textbook Dijkstra written
// here and against the default planner: the same costs on random grids of every density, with unknown cells
// and thresholds; every path legal (8-connected steps, no blocked cell, no cut corner, its steps adding up
// to its cost); tolerance, cancel, full searches and any-angle paths behave as the default's.
#include <gtest/gtest.h>

#include <atomic>
#include <cmath>
#include <random>
#include <string>
#include <vector>

#include "offload_planner_cpp/dijkstra.h"
#include "grid_checks.h"

using namespace offload_planner;
using offload_planner::test::Grid;
using offload_planner::test::expectLegalPath;
using offload_planner::test::planOn;
using offload_planner::test::referenceCost;
using offload_planner::test::with;

namespace {

}  // namespace

TEST(JumpPointSearch, NeverCutsACorner) {
  // Round the wall a diagonal step past either end would cut a blocked corner: the legal path is 5 straight
  // steps (cutting, 3 + sqrt(2)).
  Grid g({"....",
          ".##.",
          "...."});
  DijkstraPlanner planner;
  for (Algorithm a : {Algorithm::kJps, Algorithm::kAuto}) {
    const PlannerOptions o = with(a);
    const PlanResult r = planOn(planner, g, {0, 0}, {3, 2}, o);
    expectLegalPath(g, r, {0, 0}, {3, 2}, o);
    EXPECT_EQ(r.cost, 5.0) << algorithmName(a);
  }
  // Two blocks touching at a corner: the diagonal between them is no move at all.
  Grid pinch({".#",
              "#."});
  EXPECT_EQ(planOn(planner, pinch, {0, 0}, {1, 1}, with(Algorithm::kJps)).status, PlanStatus::kNoPath);
}

TEST(JumpPointSearch, SameCostsAsTheReferenceAndTheDefaultOnRandomGrids) {
  std::mt19937 rng(7);
  DijkstraPlanner jps, automatic, dijkstra;
  int compared = 0, unreachable = 0;
  for (int trial = 0; trial < 300; ++trial) {
    const double density = 0.05 * (trial % 9);  // 0 to 40 %
    Grid g(2 + static_cast<int>(rng() % 60), 2 + static_cast<int>(rng() % 60));
    std::bernoulli_distribution wall(density), unknown(0.05);
    for (auto& v : g.data) v = wall(rng) ? (unknown(rng) ? -1 : 100) : static_cast<std::int8_t>(rng() % 50);
    PlannerOptions o;
    o.unknown_is_obstacle = trial % 4 != 0;
    o.lethal_threshold = trial % 3 == 0 ? 30 : 50;
    for (int q = 0; q < 5; ++q) {
      const Cell s{static_cast<int>(rng() % g.w), static_cast<int>(rng() % g.h)};
      const Cell t{static_cast<int>(rng() % g.w), static_cast<int>(rng() % g.h)};
      g.at(s.x, s.y) = g.at(t.x, t.y) = 0;
      const double expected = referenceCost(g, s, t, o);
      const PlanResult d = planOn(dijkstra, g, s, t, o);
      for (Algorithm a : {Algorithm::kJps, Algorithm::kAuto}) {
        PlannerOptions mode = o;
        mode.algorithm = a;
        const PlanResult r = planOn(a == Algorithm::kJps ? jps : automatic, g, s, t, mode);
        if (std::isinf(expected)) {
          EXPECT_EQ(r.status, PlanStatus::kNoPath) << algorithmName(a) << " trial " << trial;
          continue;
        }
        expectLegalPath(g, r, s, t, mode);
        EXPECT_NEAR(r.cost, expected, 1e-9) << algorithmName(a) << " trial " << trial;
        EXPECT_NEAR(r.cost, d.cost, 1e-9) << algorithmName(a) << " trial " << trial;
        EXPECT_EQ(r.weighted_cost, r.cost);
      }
      std::isinf(expected) ? ++unreachable : ++compared;
    }
  }
  EXPECT_GT(compared, 800);
  EXPECT_GT(unreachable, 20);
}

TEST(JumpPointSearch, OpenGroundExpandsAFewJumpPoints) {
  Grid g(300, 200);
  for (int y = 20; y < 180; ++y) g.at(150, y) = 100;  // one wall across the middle
  DijkstraPlanner planner;
  const PlanResult d = planOn(planner, g, {10, 100}, {290, 110}, with(Algorithm::kDijkstra));
  const PlanResult j = planOn(planner, g, {10, 100}, {290, 110}, with(Algorithm::kJps));
  expectLegalPath(g, j, {10, 100}, {290, 110}, with(Algorithm::kJps));
  EXPECT_NEAR(j.cost, d.cost, 1e-9);
  EXPECT_LT(j.expansions * 100, d.expansions) << j.expansions << " jump points vs " << d.expansions << " cells";
}

TEST(JumpPointSearch, AutoTakesJumpPointsOnOpenGroundAndTheWavesInAMaze) {
  DijkstraPlanner planner;
  Grid open(200, 200);
  for (int y = 50; y < 150; ++y) open.at(100, y) = 100;
  const PlanResult waves = planOn(planner, open, {5, 100}, {195, 100}, with(Algorithm::kDijkstra));
  const PlanResult jumps = planOn(planner, open, {5, 100}, {195, 100}, with(Algorithm::kJps));
  const PlanResult open_auto = planOn(planner, open, {5, 100}, {195, 100}, with(Algorithm::kAuto));
  EXPECT_EQ(open_auto.expansions, jumps.expansions);
  EXPECT_NEAR(open_auto.cost, waves.cost, 1e-9);
  // A pillar at every other cell of every other row: no diagonal move is legal and a free/blocked boundary
  // comes every other cell, so nearly every cell would be a jump point.
  Grid maze(201, 201);
  for (int y = 1; y < maze.h; y += 2) {
    for (int x = 1; x < maze.w; x += 2) maze.at(x, y) = 100;
  }
  const PlanResult maze_waves = planOn(planner, maze, {0, 0}, {200, 200}, with(Algorithm::kDijkstra));
  const PlanResult maze_auto = planOn(planner, maze, {0, 0}, {200, 200}, with(Algorithm::kAuto));
  ASSERT_TRUE(maze_waves.ok()) << maze_waves.message;
  EXPECT_EQ(maze_auto.expansions, maze_waves.expansions);
  EXPECT_NEAR(maze_auto.cost, maze_waves.cost, 1e-9);
  // Cost-aware planning is not uniform: auto runs what the default runs, so the same costs.
  PlannerOptions weighted = with(Algorithm::kAuto);
  weighted.cost_factor = 3.0;
  PlannerOptions weighted_default = with(Algorithm::kDijkstra);
  weighted_default.cost_factor = 3.0;
  const PlanResult a = planOn(planner, open, {5, 100}, {195, 100}, weighted);
  const PlanResult b = planOn(planner, open, {5, 100}, {195, 100}, weighted_default);
  EXPECT_EQ(a.weighted_cost, b.weighted_cost);
  EXPECT_EQ(a.expansions, b.expansions);
}

TEST(JumpPointSearch, AutoTakesJumpPointsInAFoldedCorridor) {
  // A serpentine of 4-cell corridors between 1-cell walls (rows 5, 10, ..., 305), each open at alternate ends.
  // Its rows are a straight wall or free: corners only at the wall ends, where jump points come from. The
  // choice samples 32 rows 10 apart here, each on a wall row: the old measure (free/blocked boundaries per free
  // cell of the sampled rows) read it as solid clutter and ran the waves.
  DijkstraPlanner planner;
  Grid folded(400, 311);
  for (int y = 5, k = 0; y < folded.h - 1; y += 5, ++k) {
    for (int x = 0; x < folded.w; ++x) folded.at(x, y) = 100;
    folded.at(k % 2 ? 0 : folded.w - 1, y) = 0;
  }
  for (const Cell goal : {Cell{390, 303}, Cell{10, 309}, Cell{200, 201}}) {
    const PlanResult waves = planOn(planner, folded, {2, 1}, goal, with(Algorithm::kDijkstra));
    const PlanResult jumps = planOn(planner, folded, {2, 1}, goal, with(Algorithm::kJps));
    const PlanResult picked = planOn(planner, folded, {2, 1}, goal, with(Algorithm::kAuto));
    ASSERT_TRUE(waves.ok()) << waves.message;
    EXPECT_LT(jumps.expansions * 10, waves.expansions);
    EXPECT_EQ(picked.expansions, jumps.expansions) << "goal " << goal.x << ", " << goal.y;
    EXPECT_NEAR(picked.cost, waves.cost, 1e-9);
    expectLegalPath(folded, picked, {2, 1}, goal, with(Algorithm::kAuto));
  }
}

TEST(JumpPointSearch, ToleranceAndUnreachableGoalsAsTheDefault) {
  Grid g({"..........",
          "..........",
          "......###.",
          "......#.#.",
          "......###.",
          ".........."});
  DijkstraPlanner planner;
  for (Algorithm a : {Algorithm::kJps, Algorithm::kAuto}) {
    PlannerOptions o = with(a);
    // An enclosed goal: no path, and with a tolerance the nearest reachable free cell.
    EXPECT_EQ(planOn(planner, g, {0, 0}, {7, 3}, o).status, PlanStatus::kNoPath);
    o.goal_tolerance_cells = 2.0;
    PlannerOptions d = with(Algorithm::kDijkstra);
    d.goal_tolerance_cells = 2.0;
    const PlanResult r = planOn(planner, g, {0, 0}, {7, 3}, o);
    const PlanResult expected = planOn(planner, g, {0, 0}, {7, 3}, d);
    ASSERT_TRUE(r.ok()) << r.message;
    EXPECT_EQ(r.goal, expected.goal);
    EXPECT_NEAR(r.cost, expected.cost, 1e-9);
    // A blocked goal with a tolerance: the nearest free cell, reached by jump points.
    const PlanResult blocked = planOn(planner, g, {0, 0}, {6, 2}, o);
    const PlanResult blocked_default = planOn(planner, g, {0, 0}, {6, 2}, d);
    ASSERT_TRUE(blocked.ok()) << blocked.message;
    EXPECT_EQ(blocked.goal, blocked_default.goal);
    EXPECT_NEAR(blocked.cost, blocked_default.cost, 1e-9);
    expectLegalPath(g, blocked, {0, 0}, blocked.goal, o);
  }
}

TEST(JumpPointSearch, StartAtGoalFullSearchesAndCancel) {
  Grid g(40, 30);
  for (int x = 5; x < 35; ++x) g.at(x, 15) = 100;
  DijkstraPlanner planner;
  PlannerOptions o = with(Algorithm::kJps);
  const PlanResult same = planOn(planner, g, {3, 3}, {3, 3}, o);
  ASSERT_TRUE(same.ok());
  EXPECT_EQ(same.cost, 0.0);
  EXPECT_EQ(same.path.size(), 1u);
  // A full search has no goal to jump to: it is the default's wave, every reachable cell settled.
  o.stop_at_goal = false;
  PlannerOptions d = with(Algorithm::kDijkstra);
  d.stop_at_goal = false;
  const PlanResult full = planOn(planner, g, {3, 3}, {30, 25}, o);
  EXPECT_EQ(full.expansions, planOn(planner, g, {3, 3}, {30, 25}, d).expansions);
  EXPECT_EQ(full.expansions, 40u * 30u - 30u);
  std::atomic<bool> cancel{true};
  o = with(Algorithm::kJps);
  o.cancel = &cancel;
  EXPECT_EQ(planOn(planner, g, {3, 3}, {30, 25}, o).status, PlanStatus::kCancelled);
  cancel = false;
  const PlanResult after = planOn(planner, g, {3, 3}, {30, 25}, o);
  expectLegalPath(g, after, {3, 3}, {30, 25}, o);
}

TEST(JumpPointSearch, BuffersReusedAcrossMapsOfOneSizeReadOnlyTheCurrentMap) {
  // The same planner on two maps of one size: rows derived for the first must not leak into the second.
  Grid first(60, 40), second(60, 40);
  for (int y = 0; y < 39; ++y) second.at(30, y) = 100;   // a wall with a gap at the bottom only
  DijkstraPlanner planner;
  const PlannerOptions o = with(Algorithm::kJps);
  for (int round = 0; round < 3; ++round) {
    const PlanResult a = planOn(planner, first, {2, 2}, {58, 2}, o);
    EXPECT_NEAR(a.cost, 56.0, 1e-9);
    const PlanResult b = planOn(planner, second, {2, 2}, {58, 2}, o);
    EXPECT_NEAR(b.cost, referenceCost(second, {2, 2}, {58, 2}, o), 1e-9);
    expectLegalPath(second, b, {2, 2}, {58, 2}, o);
  }
}

TEST(JumpPointSearch, AnyAngleFromJumpPointsCrossesNoBlockedCellAndIsNeverLonger) {
  std::mt19937 rng(3);
  DijkstraPlanner planner;
  for (int trial = 0; trial < 30; ++trial) {
    Grid g(80, 80);
    std::bernoulli_distribution wall(0.15);
    for (auto& v : g.data) v = wall(rng) ? 100 : 0;
    const Cell s{1, 1}, t{78, 78};
    g.at(s.x, s.y) = g.at(t.x, t.y) = 0;
    PlannerOptions o = with(Algorithm::kJps);
    const PlanResult cells = planOn(planner, g, s, t, o);
    if (!cells.ok()) continue;
    o.any_angle = true;
    const PlanResult r = planOn(planner, g, s, t, o);
    ASSERT_TRUE(r.ok()) << r.message;
    EXPECT_EQ(r.path.front(), s);
    EXPECT_EQ(r.path.back(), t);
    for (std::size_t k = 1; k < r.path.size(); ++k) {
      EXPECT_TRUE(segmentClear(g.data.data(), g.w, g.h, r.path[k - 1], r.path[k], o)) << "segment " << k;
    }
    EXPECT_LE(r.cost, cells.cost + 1e-9);
  }
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
