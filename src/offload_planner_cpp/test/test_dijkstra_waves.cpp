// The core planner's two waves (from both ends, joined into one optimal path) and cancelling a plan: before
// it starts, from another thread while it runs, and during a cold planner's first plan.
#include <gtest/gtest.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <random>
#include <string>
#include <thread>
#include <vector>

#include "dijkstra_grid.h"

using namespace offload_planner;
using test::DijkstraOptions;
using test::Grid;
using test::expectValidPath;
using test::kSqrt2;
using test::referenceCost;

// The default search runs from both ends; its two halves must join into one legal, optimal path.
TEST(Dijkstra, TheTwoWavesJoinIntoALegalOptimalPath) {
  std::mt19937 rng(11);
  int checked = 0;
  for (int trial = 0; trial < 40; ++trial) {
    const int w = 30 + static_cast<int>(rng() % 90), h = 30 + static_cast<int>(rng() % 90);
    std::bernoulli_distribution blocked(0.05 + 0.1 * (trial % 4));
    Grid grid(std::vector<std::string>(h, std::string(w, '.')));
    for (auto& v : grid.data) v = blocked(rng) ? 100 : 0;
    for (int q = 0; q < 5; ++q) {
      Cell s{static_cast<int>(rng() % w), static_cast<int>(rng() % h)};
      Cell g{static_cast<int>(rng() % w), static_cast<int>(rng() % h)};
      grid.data[s.y * w + s.x] = 0;
      grid.data[g.y * w + g.x] = 0;
      const double expected = referenceCost(grid.data, w, h, s, g);
      const auto r = grid.plan(s, g);
      if (std::isinf(expected)) {
        EXPECT_EQ(r.status, PlanStatus::kNoPath);
        continue;
      }
      expectValidPath(grid, r, s, g);
      EXPECT_NEAR(r.cost, expected, 1e-9) << "trial " << trial << " query " << q;
      ++checked;
    }
  }
  EXPECT_GT(checked, 120);
}

TEST(Dijkstra, TwoWavesSettleAboutHalfTheCellsOfOne) {
  Grid grid(std::vector<std::string>(201, std::string(201, '.')));
  const Cell s{50, 100}, g{150, 100};
  const auto r = grid.plan(s, g);
  expectValidPath(grid, r, s, g);
  EXPECT_NEAR(r.cost, 100.0, 1e-9);
  // One wave from s settles every cell nearer than the goal (octile distance below 100) before the goal.
  std::uint64_t one_wave = 0;
  for (int y = 0; y < 201; ++y) {
    for (int x = 0; x < 201; ++x) {
      const double dx = std::abs(x - s.x), dy = std::abs(y - s.y);
      one_wave += std::max(dx, dy) + (kSqrt2 - 1.0) * std::min(dx, dy) < 100.0;
    }
  }
  EXPECT_LT(r.expansions, 0.65 * one_wave) << one_wave << " cells in one wave";
}

TEST(Dijkstra, AnEnclosedGoalIsProvedUnreachableByItsOwnWave) {
  std::vector<std::string> rows(200, std::string(200, '.'));
  for (int k = 150; k <= 154; ++k) rows[150][k] = rows[154][k] = rows[k][150] = rows[k][154] = '#';
  Grid grid(rows);
  const auto r = grid.plan({0, 0}, {152, 152});
  EXPECT_EQ(r.status, PlanStatus::kNoPath);
  EXPECT_LT(r.expansions, 50u) << "the goal's wave runs dry inside the box; the start's need not cover the map";
  // With a tolerance, the nearest reachable cell needs the start's whole component: still found.
  DijkstraOptions tolerant;
  tolerant.goal_tolerance_cells = 3.0;
  const auto near = grid.plan({0, 0}, {152, 152}, tolerant);
  ASSERT_TRUE(near.ok()) << near.message;
  const double dx = near.goal.x - 152, dy = near.goal.y - 152;
  EXPECT_NEAR(std::hypot(dx, dy), 3.0, 1e-9);
  expectValidPath(grid, near, {0, 0}, near.goal);
}

TEST(Dijkstra, AStartWaveThatRanDryIsNotRepeatedForTheTolerance) {
  // A wall cuts off a small room around the start; the goal lies just beyond it. The start's wave runs dry
  // first and has settled everything the tolerance may choose from: no second flood of the room.
  std::vector<std::string> rows(100, std::string(200, '.'));
  for (auto& row : rows) row[20] = '#';
  Grid grid(rows);
  const auto plain = grid.plan({10, 50}, {22, 50});
  EXPECT_EQ(plain.status, PlanStatus::kNoPath);
  DijkstraOptions tolerant;
  tolerant.goal_tolerance_cells = 3.0;
  const auto near = grid.plan({10, 50}, {22, 50}, tolerant);
  ASSERT_TRUE(near.ok()) << near.message;
  EXPECT_EQ(near.goal, (Cell{19, 50}));
  expectValidPath(grid, near, {10, 50}, {19, 50});
  EXPECT_EQ(near.expansions, plain.expansions) << "the start's room was flooded twice";
}

TEST(Dijkstra, ACancelSetBeforehandStopsThePlanAtOnce) {
  Grid g(std::vector<std::string>(50, std::string(50, '.')));
  std::atomic<bool> cancel{true};
  DijkstraOptions o;
  o.cancel = &cancel;
  const auto r = g.plan({0, 0}, {49, 49}, o);
  EXPECT_EQ(r.status, PlanStatus::kCancelled);
  EXPECT_EQ(r.expansions, 0u);
  EXPECT_TRUE(r.path.empty());
  EXPECT_NE(r.message.find("cancelled"), std::string::npos);
  cancel = false;   // a flag that is never set changes nothing, and the buffers are clean for the next plan
  const auto again = g.plan({0, 0}, {49, 49}, o);
  ASSERT_TRUE(again.ok()) << again.message;
  EXPECT_NEAR(again.cost, 49 * kSqrt2, 1e-9);
}

TEST(Dijkstra, ACancelFromAnotherThreadStopsARunningPlan) {
  // A full wave over 4 M cells takes tens of milliseconds; the cancel comes once it has started.
  const int n = 2000;
  std::vector<std::int8_t> grid(static_cast<std::size_t>(n) * n, 0);
  DijkstraPlanner planner;
  ASSERT_TRUE(planner.plan(grid.data(), grid.size(), n, n, {0, 0}, {2, 2}, DijkstraOptions()).ok());   // buffers allocated
  DijkstraOptions o;
  o.stop_at_goal = false;
  std::atomic<bool> cancel{false};
  o.cancel = &cancel;
  std::thread canceller([&] {
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
    cancel = true;
  });
  const auto r = planner.plan(grid.data(), grid.size(), n, n, {0, 0}, {n - 1, n - 1}, o);
  canceller.join();
  ASSERT_EQ(r.status, PlanStatus::kCancelled) << r.message;
  EXPECT_GT(r.expansions, 0u);
  EXPECT_LT(r.expansions, grid.size());
  EXPECT_EQ(r.expansions % 4096, 0u) << "stopped at a check";
  // The next plan on the same planner is exact: the cancelled search's rows were reset.
  cancel = false;
  const auto after = planner.plan(grid.data(), grid.size(), n, n, {0, 0}, {10, 3}, o);
  ASSERT_TRUE(after.ok()) << after.message;
  EXPECT_NEAR(after.cost, 7 + 3 * kSqrt2, 1e-9);
  EXPECT_EQ(after.expansions, grid.size());
}

TEST(Dijkstra, ACancelDuringAColdPlannersFirstPlanStopsItAndTheNextPlansStayExact) {
  // A cold planner's first plan on a big map allocates 256 MB of wave buffers here and derives their rows as
  // the waves reach them. The cancel comes during that first plan; the rows it derived must not leak into
  // the next plans.
  const int n = 4000;
  std::vector<std::int8_t> grid(static_cast<std::size_t>(n) * n, 0);
  for (int y = 0; y < n - 1; ++y) grid[static_cast<std::size_t>(y) * n + n / 2] = 100;   // a wall with a gap
  DijkstraPlanner planner;
  // A plan on a smaller map first leaves settled (negative) distances in both buffers, where the big map's
  // first cells lie.
  const int small = 300;
  std::vector<std::int8_t> open_map(static_cast<std::size_t>(small) * small, 0);
  ASSERT_TRUE(planner.plan(open_map.data(), open_map.size(), small, small, {0, 0}, {small - 1, small - 1},
                           DijkstraOptions()).ok());
  DijkstraOptions o;
  std::atomic<bool> cancel{false};
  o.cancel = &cancel;
  std::thread canceller([&] {
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
    cancel = true;
  });
  const auto r = planner.plan(grid.data(), grid.size(), n, n, {0, 0}, {n - 1, 0}, o);
  canceller.join();
  ASSERT_EQ(r.status, PlanStatus::kCancelled) << r.message;
  EXPECT_LT(r.expansions, grid.size() / 2);
  cancel = false;
  DijkstraPlanner fresh;
  for (const Cell goal : {Cell{n - 1, 0}, Cell{3, 5}, Cell{n - 1, n - 1}}) {
    const auto after = planner.plan(grid.data(), grid.size(), n, n, {0, 0}, goal, o);
    const auto expected = fresh.plan(grid.data(), grid.size(), n, n, {0, 0}, goal, DijkstraOptions());
    ASSERT_TRUE(after.ok()) << after.message;
    EXPECT_DOUBLE_EQ(after.cost, expected.cost);
    EXPECT_EQ(after.expansions, expected.expansions);
  }
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
