// A* on buckets (algorithm astar at uniform cost, and what auto takes on random clutter) against a textbook
// Dijkstra written here: the same costs on random grids of every density, with unknown cells and thresholds,
// and on grids big enough that cells are reopened; every path legal (8-connected steps, no blocked cell, no
// cut corner, its steps adding up to its cost); unreachable goals, tolerance and cancel as the default's.
#include <gtest/gtest.h>

#include <atomic>
#include <cmath>
#include <cstdio>
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

Grid randomGrid(std::mt19937* rng, int w, int h, double density) {
  Grid g(w, h);
  std::bernoulli_distribution wall(density), unknown(0.05);
  for (auto& v : g.data) v = wall(*rng) ? (unknown(*rng) ? -1 : 100) : static_cast<std::int8_t>((*rng)() % 50);
  return g;
}

}  // namespace

TEST(BucketAStar, NeverCutsACorner) {
  Grid g(4, 3);
  g.at(1, 1) = g.at(2, 1) = 100;  // a diagonal step past either end of the wall would cut its corner
  DijkstraPlanner planner;
  const PlanResult r = planOn(planner, g, {0, 0}, {3, 2}, with(Algorithm::kAStar));
  expectLegalPath(g, r, {0, 0}, {3, 2}, with(Algorithm::kAStar));
  EXPECT_EQ(r.cost, 5.0);
  Grid pinch(2, 2);
  pinch.at(1, 0) = pinch.at(0, 1) = 100;  // two blocks touching at a corner: no move between the free cells
  EXPECT_EQ(planOn(planner, pinch, {0, 0}, {1, 1}, with(Algorithm::kAStar)).status, PlanStatus::kNoPath);
}

TEST(BucketAStar, SameCostsAsTheReferenceOnRandomGridsOfEveryDensity) {
  std::mt19937 rng(5);
  DijkstraPlanner astar;  // one planner throughout: its buffers are reused across sizes and maps
  int compared = 0, unreachable = 0;
  for (int trial = 0; trial < 300; ++trial) {
    const double density = 0.05 * (trial % 9);  // 0 to 40 %
    Grid g = randomGrid(&rng, 2 + static_cast<int>(rng() % 70), 2 + static_cast<int>(rng() % 70), density);
    PlannerOptions o = with(Algorithm::kAStar);
    o.unknown_is_obstacle = trial % 4 != 0;
    o.lethal_threshold = trial % 3 == 0 ? 30 : 50;
    for (int q = 0; q < 5; ++q) {
      const Cell s{static_cast<int>(rng() % g.w), static_cast<int>(rng() % g.h)};
      const Cell t{static_cast<int>(rng() % g.w), static_cast<int>(rng() % g.h)};
      g.at(s.x, s.y) = g.at(t.x, t.y) = 0;
      const double expected = referenceCost(g, s, t, o);
      const PlanResult r = planOn(astar, g, s, t, o);
      if (std::isinf(expected)) {
        EXPECT_EQ(r.status, PlanStatus::kNoPath) << "trial " << trial;
        ++unreachable;
        continue;
      }
      expectLegalPath(g, r, s, t, o);
      EXPECT_NEAR(r.cost, expected, 1e-9) << "trial " << trial;
      EXPECT_EQ(r.weighted_cost, r.cost);
      ++compared;
    }
  }
  EXPECT_GT(compared, 800);
  EXPECT_GT(unreachable, 20);
}

// Long paths through clutter, where a cell taken from a bucket is often improved later through another cell of
// the same bucket: a search that did not reopen it, or stopped before every f below the best cost was taken,
// returns a longer path here.
TEST(BucketAStar, ExactOnLongPathsThroughClutter) {
  std::mt19937 rng(21);
  DijkstraPlanner astar, waves;
  int compared = 0;
  for (int trial = 0; trial < 12; ++trial) {
    const double density = 0.1 + 0.05 * (trial % 5);  // 10 to 30 %
    Grid g = randomGrid(&rng, 300, 240, density);
    for (int q = 0; q < 3; ++q) {
      const Cell s{static_cast<int>(rng() % 40), static_cast<int>(rng() % g.h)};
      const Cell t{g.w - 1 - static_cast<int>(rng() % 40), static_cast<int>(rng() % g.h)};
      g.at(s.x, s.y) = g.at(t.x, t.y) = 0;
      const PlannerOptions o = with(Algorithm::kAStar);
      const double expected = referenceCost(g, s, t, o);
      if (std::isinf(expected)) continue;
      const PlanResult r = planOn(astar, g, s, t, o);
      expectLegalPath(g, r, s, t, o);
      EXPECT_NEAR(r.cost, expected, 1e-9) << "trial " << trial << " query " << q;
      const PlanResult d = planOn(waves, g, s, t, with(Algorithm::kDijkstra));
      EXPECT_LT(r.expansions, d.expansions) << "trial " << trial;  // its band, not the waves' discs
      ++compared;
    }
  }
  EXPECT_GT(compared, 25);
}

// Few cells expanded twice: a move that raises f raises it by at least 2 - sqrt 2, so with buckets of width one
// half only moves that keep f reopen a cell. Against A* on a heap over the same grid (uniform weights, so the
// same octile heuristic, each cell settled once) on these grids, width one expanded 10.9 % more, one half 3.0 %.
TEST(BucketAStar, ReopensFewCells) {
  std::mt19937 rng(8);
  DijkstraPlanner buckets, heap;
  std::uint64_t on_buckets = 0, on_heap = 0;
  for (int trial = 0; trial < 4; ++trial) {
    Grid g(400, 400);
    std::bernoulli_distribution wall(0.2);
    for (auto& v : g.data) v = wall(rng) ? 100 : 0;
    const Cell s{static_cast<int>(rng() % 40), static_cast<int>(rng() % 400)};
    const Cell t{359 + static_cast<int>(rng() % 40), static_cast<int>(rng() % 400)};
    g.at(s.x, s.y) = g.at(t.x, t.y) = 0;
    PlannerOptions weighted = with(Algorithm::kAStar);
    weighted.cost_factor = 1.0;  // every free cell is 0: each weight is neutral_cost, the heap's A*
    const PlanResult b = planOn(buckets, g, s, t, with(Algorithm::kAStar));
    const PlanResult h = planOn(heap, g, s, t, weighted);
    if (!h.ok()) continue;
    ASSERT_TRUE(b.ok()) << b.message;
    EXPECT_NEAR(b.cost * weighted.neutral_cost, h.weighted_cost, 1e-9 * h.weighted_cost);
    on_buckets += b.expansions;
    on_heap += h.expansions;
  }
  std::printf("bucket A* %llu expansions, heap A* %llu\n", static_cast<unsigned long long>(on_buckets),
              static_cast<unsigned long long>(on_heap));
  ASSERT_GT(on_heap, 50000u);
  EXPECT_LT(static_cast<double>(on_buckets), 1.05 * static_cast<double>(on_heap));
}

TEST(BucketAStar, UnreachableGoalsToleranceAndCancelAsTheDefault) {
  DijkstraPlanner astar, waves;
  Grid g(60, 40);
  for (int y = 10; y <= 30; ++y) g.at(30, y) = g.at(50, y) = 100;  // a closed box x 30-50, y 10-30
  for (int x = 30; x <= 50; ++x) g.at(x, 10) = g.at(x, 30) = 100;
  const PlanResult shut = planOn(astar, g, {2, 2}, {40, 20}, with(Algorithm::kAStar));
  EXPECT_EQ(shut.status, PlanStatus::kNoPath);
  for (double tolerance : {3.0, 12.0}) {
    PlannerOptions a = with(Algorithm::kAStar), d = with(Algorithm::kDijkstra);
    a.goal_tolerance_cells = d.goal_tolerance_cells = tolerance;
    const PlanResult ra = planOn(astar, g, {2, 2}, {40, 20}, a);
    const PlanResult rd = planOn(waves, g, {2, 2}, {40, 20}, d);
    ASSERT_EQ(ra.status, rd.status) << ra.message;
    if (!rd.ok()) continue;
    EXPECT_EQ(ra.goal, rd.goal);
    EXPECT_NEAR(ra.cost, rd.cost, 1e-9);
  }
  std::atomic<bool> cancel{true};
  PlannerOptions a = with(Algorithm::kAStar);
  a.cancel = &cancel;
  EXPECT_EQ(planOn(astar, g, {2, 2}, {58, 38}, a).status, PlanStatus::kCancelled);
  cancel = false;
  const PlanResult after = planOn(astar, g, {2, 2}, {58, 38}, a);
  ASSERT_TRUE(after.ok()) << after.message;
  EXPECT_NEAR(after.cost, referenceCost(g, {2, 2}, {58, 38}, a), 1e-9);
}

// auto: A* on buckets on random clutter (0.61 corners per free cell at 20 %, 0.82 at 30 %), jump points on
// structured maps and the waves in a maze (below, and test_jump_point_search.cpp), each with the default's costs.
TEST(BucketAStar, AutoTakesItOnRandomClutter) {
  std::mt19937 rng(3);
  DijkstraPlanner planner;
  for (double density : {0.1, 0.2, 0.25, 0.3}) {
    Grid g(400, 400);
    std::bernoulli_distribution wall(density);
    for (auto& v : g.data) v = wall(rng) ? 100 : 0;
    g.at(1, 1) = g.at(398, 398) = 0;
    const PlanResult picked = planOn(planner, g, {1, 1}, {398, 398}, with(Algorithm::kAuto));
    const PlanResult astar = planOn(planner, g, {1, 1}, {398, 398}, with(Algorithm::kAStar));
    const PlanResult waves = planOn(planner, g, {1, 1}, {398, 398}, with(Algorithm::kDijkstra));
    ASSERT_TRUE(waves.ok()) << waves.message;
    EXPECT_EQ(picked.expansions, astar.expansions) << "density " << density;
    EXPECT_NEAR(picked.cost, waves.cost, 1e-9);
    expectLegalPath(g, picked, {1, 1}, {398, 398}, with(Algorithm::kAuto));
  }
}

// A maze of one-cell corridors reads as many corners per free cell as 25 % clutter, but its walls are long:
// few corners per blocked cell, and A* there takes 3.5x the waves' time (maze512-1-0), so auto takes the waves.
TEST(BucketAStar, AutoTakesTheWavesInAMazeOfCorridors) {
  constexpr int kCells = 100;  // the maze's rooms, at odd coordinates, carved by a depth-first walk
  Grid g(2 * kCells + 1, 2 * kCells + 1);
  for (auto& v : g.data) v = 100;
  std::mt19937 rng(4);
  std::vector<char> seen(kCells * kCells, 0);
  std::vector<int> stack{0};
  seen[0] = 1;
  g.at(1, 1) = 0;
  while (!stack.empty()) {
    const int c = stack.back();
    const int cx = c % kCells, cy = c / kCells;
    int next[4], n = 0;
    const int dx[4] = {1, -1, 0, 0}, dy[4] = {0, 0, 1, -1};
    for (int k = 0; k < 4; ++k) {
      const int nx = cx + dx[k], ny = cy + dy[k];
      if (nx >= 0 && ny >= 0 && nx < kCells && ny < kCells && !seen[ny * kCells + nx]) next[n++] = k;
    }
    if (n == 0) {
      stack.pop_back();
      continue;
    }
    const int k = next[rng() % n];
    const int nx = cx + dx[k], ny = cy + dy[k];
    seen[ny * kCells + nx] = 1;
    g.at(2 * cx + 1 + dx[k], 2 * cy + 1 + dy[k]) = g.at(2 * nx + 1, 2 * ny + 1) = 0;
    stack.push_back(ny * kCells + nx);
  }
  DijkstraPlanner planner;
  const Cell s{1, 1}, t{2 * kCells - 1, 2 * kCells - 1};
  const PlanResult picked = planOn(planner, g, s, t, with(Algorithm::kAuto));
  const PlanResult waves = planOn(planner, g, s, t, with(Algorithm::kDijkstra));
  const PlanResult astar = planOn(planner, g, s, t, with(Algorithm::kAStar));
  ASSERT_TRUE(waves.ok()) << waves.message;
  EXPECT_EQ(picked.expansions, waves.expansions);
  EXPECT_NE(astar.expansions, waves.expansions);  // the check above tells the two apart
  EXPECT_NEAR(picked.cost, waves.cost, 1e-9);
  EXPECT_NEAR(astar.cost, waves.cost, 1e-9);
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
