// The planner's options on random grids against independent references written here: A* (same costs
// as Dijkstra, fewer cells), cost-aware planning (a textbook weighted Dijkstra on the same graph),
// inflation (a brute-force distance), and any-angle paths (segment-square intersection, never costlier).
#include <gtest/gtest.h>

#include <algorithm>
#include <cstdio>
#include <cmath>
#include <random>
#include <vector>

#include "offload_planner_cpp/dijkstra.h"
#include "offload_planner_cpp/inflation.h"
#include "reference_any_angle.h"
#include "reference_search.h"

using namespace offload_planner;

namespace {

const double kSqrt2 = std::sqrt(2.0);

struct RandomGrid {
  int w, h;
  std::vector<std::int8_t> data;
  RandomGrid(std::mt19937* rng, int width, int height, double blocked, bool graded) : w(width), h(height) {
    std::bernoulli_distribution wall(blocked);
    std::uniform_int_distribution<int> occupancy(0, 49);
    data.resize(static_cast<std::size_t>(w) * h);
    for (auto& v : data) v = wall(*rng) ? 100 : graded ? occupancy(*rng) : 0;
  }
  // A cell drawn uniformly (x first, then y, as every test here draws them).
  Cell randomCell(std::mt19937* rng) const {
    const int x = static_cast<int>((*rng)() % w);
    return {x, static_cast<int>((*rng)() % h)};
  }
  void open(Cell c) { data[c.y * w + c.x] = 0; }
  bool free(int x, int y, int lethal = 50) const {
    return x >= 0 && y >= 0 && x < w && y < h && data[y * w + x] >= 0 && data[y * w + x] < lethal;
  }
};

// Textbook weighted Dijkstra: a move between a and b costs its length times the mean of their weights.
double referenceCost(const RandomGrid& g, Cell s, Cell t, double neutral, double factor) {
  auto weight = [&](int i) { return neutral + factor * std::max<int>(g.data[i], 0); };
  return test::referenceCost(g.w, g.h, s, t, [&](int x, int y) { return g.free(x, y); },
                             [&](int i, int j) { return 0.5 * (weight(i) + weight(j)); });
}

// Every segment of an any-angle path meets only free cells, and the path runs from s to t.
void expectClearPath(const RandomGrid& g, const PlanResult& r, Cell s, Cell t) {
  ASSERT_TRUE(r.ok()) << r.message;
  EXPECT_EQ(r.path.front(), s);
  EXPECT_EQ(r.path.back(), t);
  double length = 0.0;
  for (std::size_t k = 1; k < r.path.size(); ++k) {
    const Cell a = r.path[k - 1], b = r.path[k];
    length += std::hypot(b.x - a.x, b.y - a.y);
    const Cell blocked = test::firstBlockedOn(a, b, [&](int x, int y) { return g.free(x, y); });
    ASSERT_LT(blocked.x, 0) << "segment " << k << " (" << a.x << "," << a.y << ")-(" << b.x << "," << b.y
                            << ") meets blocked cell (" << blocked.x << "," << blocked.y << ")";
  }
  EXPECT_NEAR(length, r.cost, 1e-9);
}

}  // namespace

TEST(PlannerModes, AStarHasDijkstrasCostsAndSettlesFewerCells) {
  std::mt19937 rng(11);
  DijkstraPlanner dijkstra, astar;
  PlannerOptions a;
  a.algorithm = Algorithm::kAStar;
  std::uint64_t settled_dijkstra = 0, settled_astar = 0;
  int compared = 0;
  for (int trial = 0; trial < 40; ++trial) {
    RandomGrid g(&rng, 20 + rng() % 80, 20 + rng() % 80, 0.1 + 0.1 * (trial % 3), trial % 2 == 1);
    for (int q = 0; q < 5; ++q) {
      const Cell s = g.randomCell(&rng), t = g.randomCell(&rng);
      g.open(s);
      g.open(t);
      for (double factor : {0.0, 3.0}) {
        PlannerOptions d;
        d.algorithm = Algorithm::kDijkstra;
        d.cost_factor = a.cost_factor = factor;
        const auto rd = dijkstra.plan(g.data.data(), g.data.size(), g.w, g.h, s, t, d);
        const auto ra = astar.plan(g.data.data(), g.data.size(), g.w, g.h, s, t, a);
        ASSERT_EQ(rd.status, ra.status) << ra.message;
        if (!rd.ok()) continue;
        EXPECT_NEAR(ra.weighted_cost, rd.weighted_cost, 1e-9 * std::max(1.0, rd.weighted_cost));
        settled_dijkstra += rd.expansions;
        settled_astar += ra.expansions;
        ++compared;
      }
    }
  }
  EXPECT_GT(compared, 200);
  EXPECT_LT(settled_astar * 2, settled_dijkstra) << "A* settles far fewer cells";
}

TEST(PlannerModes, CostAwareMatchesAWeightedReferenceAndUniformIsUnchanged) {
  std::mt19937 rng(5);
  DijkstraPlanner planner;
  int checked = 0;
  for (int trial = 0; trial < 40; ++trial) {
    RandomGrid g(&rng, 10 + rng() % 60, 10 + rng() % 60, 0.15, true);
    for (int q = 0; q < 5; ++q) {
      const Cell s = g.randomCell(&rng), t = g.randomCell(&rng);
      g.open(s);
      g.open(t);
      PlannerOptions o;
      o.cost_factor = 3.0;
      o.neutral_cost = 50.0;
      const double expected = referenceCost(g, s, t, 50.0, 3.0);
      const auto r = planner.plan(g.data.data(), g.data.size(), g.w, g.h, s, t, o);
      if (std::isinf(expected)) {
        EXPECT_EQ(r.status, PlanStatus::kNoPath);
        continue;
      }
      ASSERT_TRUE(r.ok()) << r.message;
      EXPECT_NEAR(r.weighted_cost, expected, 1e-9 * expected);
      // The traced path is one of that cost, and cost is its length.
      double cost = 0.0, length = 0.0;
      for (std::size_t k = 1; k < r.path.size(); ++k) {
        const Cell a = r.path[k - 1], b = r.path[k];
        const double step = (a.x != b.x && a.y != b.y) ? kSqrt2 : 1.0;
        length += step;
        cost += step * 0.5 * (100.0 + 3.0 * (g.data[a.y * g.w + a.x] + g.data[b.y * g.w + b.x]));
      }
      EXPECT_NEAR(cost, expected, 1e-9 * expected);
      EXPECT_NEAR(length, r.cost, 1e-9);
      // Uniform cost (factor 0) is the plain length, whatever the occupancy of passable cells.
      const auto uniform = planner.plan(g.data.data(), g.data.size(), g.w, g.h, s, t);
      EXPECT_NEAR(uniform.weighted_cost, uniform.cost, 0.0);
      EXPECT_LE(uniform.cost, r.cost + 1e-9);
      ++checked;
    }
  }
  EXPECT_GT(checked, 100);
}

TEST(PlannerModes, CostAwarePathsKeepAwayFromHighCost) {
  // A corridor of occupancy 40 on the straight line and a free detour two cells longer: the cost-aware
  // plan takes the detour, the uniform one the corridor.
  const int w = 9, h = 5;
  std::vector<std::int8_t> grid(w * h, 100);
  for (int x = 0; x < w; ++x) grid[2 * w + x] = 40;                 // the direct row, costly
  for (int x = 1; x < w - 1; ++x) grid[0 * w + x] = 0;              // a free row above
  for (int x : {0, w - 1}) grid[1 * w + x] = grid[0 * w + x] = 0;   // joined at both ends
  grid[2 * w] = grid[2 * w + w - 1] = 0;
  DijkstraPlanner planner;
  PlannerOptions o;
  o.cost_factor = 3.0;
  const auto costly = planner.plan(grid.data(), grid.size(), w, h, {0, 2}, {w - 1, 2});
  const auto aware = planner.plan(grid.data(), grid.size(), w, h, {0, 2}, {w - 1, 2}, o);
  ASSERT_TRUE(costly.ok() && aware.ok());
  EXPECT_NEAR(costly.cost, w - 1, 1e-9);
  EXPECT_GT(aware.cost, costly.cost);
  for (const Cell c : aware.path) {
    if (c.x > 0 && c.x < w - 1) {
      EXPECT_NE(c.y, 2) << "the cost-aware path stays off the costly row";
    }
  }
}

TEST(PlannerModes, DistanceTransformIsExact) {
  std::mt19937 rng(3);
  for (int trial = 0; trial < 20; ++trial) {
    RandomGrid g(&rng, 5 + rng() % 40, 5 + rng() % 40, trial == 0 ? 0.0 : 0.05, false);
    std::vector<double> d2;
    obstacleDistanceSquared(g.data.data(), g.w, g.h, PlannerOptions(), &d2);
    for (int y = 0; y < g.h; ++y) {
      for (int x = 0; x < g.w; ++x) {
        double best = INFINITY;
        for (int v = 0; v < g.h; ++v) {
          for (int u = 0; u < g.w; ++u) {
            if (!g.free(u, v)) best = std::min(best, double(u - x) * (u - x) + double(v - y) * (v - y));
          }
        }
        ASSERT_EQ(d2[y * g.w + x], best) << "cell (" << x << ", " << y << ")";
      }
    }
  }
}

TEST(PlannerModes, InflationBlocksTheRobotRadiusAndGradesBeyond) {
  const int w = 21, h = 3;
  std::vector<std::int8_t> grid(w * h, 0);
  grid[1 * w + 0] = 100;  // one obstacle at the left end of the middle row
  PlannerOptions o;
  o.robot_radius_cells = 2.0;
  o.inflation_radius_cells = 8.0;
  std::vector<std::int8_t> out;
  inflate(grid.data(), w, h, o, &out);
  EXPECT_EQ(out[1 * w + 0], 100);
  EXPECT_EQ(out[1 * w + 1], 100);
  EXPECT_EQ(out[1 * w + 2], 100);   // d = 2: inscribed
  EXPECT_EQ(out[1 * w + 3], std::round(49 * std::exp(-0.5)));
  for (int x = 4; x <= 8; ++x) EXPECT_LT(out[1 * w + x], out[1 * w + x - 1]);
  EXPECT_EQ(out[1 * w + 9], 0);     // beyond the inflation radius
  for (int x = 3; x < w; ++x) EXPECT_LT(out[1 * w + x], 50) << "inflated cells stay passable";
  // Planning with inflation goes around the inscribed cells.
  DijkstraPlanner planner;
  EXPECT_EQ(planner.plan(grid.data(), grid.size(), w, h, {1, 0}, {20, 0}, o).status, PlanStatus::kStartBlocked);
}

TEST(PlannerModes, AnyAngleCrossesNoBlockedCellAndIsNeverLonger) {
  std::mt19937 rng(17);
  DijkstraPlanner planner;
  double grid_length = 0.0, pulled_length = 0.0;
  int checked = 0;
  for (int trial = 0; trial < 30; ++trial) {
    RandomGrid g(&rng, 30 + rng() % 70, 30 + rng() % 70, 0.2, trial % 2 == 1);
    for (int q = 0; q < 5; ++q) {
      const Cell s = g.randomCell(&rng), t = g.randomCell(&rng);
      g.open(s);
      g.open(t);
      for (double factor : {0.0, 3.0}) {
        PlannerOptions o;
        o.cost_factor = factor;
        const auto cells = planner.plan(g.data.data(), g.data.size(), g.w, g.h, s, t, o);
        if (!cells.ok()) continue;
        o.any_angle = true;
        const auto pulled = planner.plan(g.data.data(), g.data.size(), g.w, g.h, s, t, o);
        expectClearPath(g, pulled, s, t);
        EXPECT_LE(pulled.weighted_cost, cells.weighted_cost * (1 + 1e-9)) << "never costlier";
        if (factor == 0.0) {
          EXPECT_LE(pulled.cost, cells.cost + 1e-9);
          EXPECT_EQ(pulled.weighted_cost, pulled.cost) << "at uniform cost, the length itself";
          grid_length += cells.cost;
          pulled_length += pulled.cost;
        }
        ++checked;
      }
    }
  }
  EXPECT_GT(checked, 100);
  EXPECT_LT(pulled_length, grid_length);
}

TEST(PlannerModes, AnyAngleIsAtLeastFourPercentShorterOnRandomMaps) {
  // 20 % random obstacles, pairs at least 60 cells apart: the bar, also checked from Python.
  std::mt19937 rng(23);
  DijkstraPlanner planner;
  double octile = 0.0, pulled = 0.0;
  int pairs = 0;
  for (int trial = 0; trial < 12; ++trial) {
    RandomGrid g(&rng, 160, 160, 0.2, false);
    for (int q = 0; q < 8; ++q) {
      const Cell s = g.randomCell(&rng), t = g.randomCell(&rng);
      if (std::hypot(s.x - t.x, s.y - t.y) < 60) continue;
      g.data[s.y * g.w + s.x] = g.data[t.y * g.w + t.x] = 0;
      const auto cells = planner.plan(g.data.data(), g.data.size(), g.w, g.h, s, t);
      if (!cells.ok()) continue;
      PlannerOptions o;
      o.any_angle = true;
      const auto tight = planner.plan(g.data.data(), g.data.size(), g.w, g.h, s, t, o);
      expectClearPath(g, tight, s, t);
      octile += cells.cost;
      pulled += tight.cost;
      ++pairs;
    }
  }
  ASSERT_GT(pairs, 40);
  const double saving = 1.0 - pulled / octile;
  std::printf("any-angle: %d pairs, %.2f %% shorter than the 8-connected optimum\n", pairs, 100 * saving);
  EXPECT_GE(saving, 0.04);
}

TEST(PlannerModes, AnyAngleTouchesNoBlockedCornerAmongPillars) {
  // Single blocked cells on a lattice: lines between cell centres run exactly through their corners all the
  // time, where the corner rule (touching counts) decides. A path that slips past one fails here.
  DijkstraPlanner planner;
  std::mt19937 rng(31);
  int checked = 0;
  for (int spacing : {2, 3, 4, 5}) {
    RandomGrid g(&rng, 61, 47, 0.0, false);
    for (int y = 1; y < g.h; y += spacing) {
      for (int x = 1 + (y / spacing) % 2; x < g.w; x += spacing) g.data[y * g.w + x] = 100;
    }
    for (int q = 0; q < 30; ++q) {
      const Cell s = g.randomCell(&rng), t = g.randomCell(&rng);
      if (!g.free(s.x, s.y) || !g.free(t.x, t.y)) continue;
      const auto cells = planner.plan(g.data.data(), g.data.size(), g.w, g.h, s, t);
      if (!cells.ok()) continue;
      PlannerOptions o;
      o.any_angle = true;
      const auto tight = planner.plan(g.data.data(), g.data.size(), g.w, g.h, s, t, o);
      expectClearPath(g, tight, s, t);
      EXPECT_LE(tight.cost, cells.cost + 1e-9) << "longer than the 8-connected optimum";
      ++checked;
    }
  }
  EXPECT_GT(checked, 80);
}

TEST(PlannerModes, AnyAngleAlongFoldedCorridorsCutsNoCorner) {
  // A serpentine of 3-cell lanes 1500 cells long, single teeth on the walls: paths of long straight runs,
  // which are pulled turn by turn (any_angle.cpp), each U-turn a wall end a segment could slip past.
  DijkstraPlanner planner;
  std::mt19937 rng(43);
  RandomGrid g(&rng, 1500, 49, 0.0, false);
  for (int y = 4; y < g.h; y += 4) {
    for (int x = 0; x < g.w; ++x) g.data[y * g.w + x] = 100;
    const int gap = (y / 4) % 2 == 0 ? 0 : g.w - 4;  // the way through, at alternating ends
    for (int x = gap; x < gap + 4; ++x) g.data[y * g.w + x] = 0;
    for (int x = 20 + static_cast<int>(rng() % 40); x < g.w - 20; x += 37 + static_cast<int>(rng() % 60)) {
      g.data[(y - 1) * g.w + x] = 100;  // a tooth under the wall
    }
  }
  int checked = 0;
  for (int q = 0; q < 16; ++q) {
    const Cell s{static_cast<int>(rng() % g.w), static_cast<int>(rng() % 3)};
    const Cell t{static_cast<int>(rng() % g.w), g.h - 4 + static_cast<int>(rng() % 3)};
    if (!g.free(s.x, s.y) || !g.free(t.x, t.y)) continue;
    const auto cells = planner.plan(g.data.data(), g.data.size(), g.w, g.h, s, t);
    ASSERT_TRUE(cells.ok()) << cells.message;
    PlannerOptions o;
    o.any_angle = true;
    const auto tight = planner.plan(g.data.data(), g.data.size(), g.w, g.h, s, t, o);
    expectClearPath(g, tight, s, t);
    EXPECT_LE(tight.cost, cells.cost + 1e-9) << "longer than the 8-connected optimum";
    EXPECT_LT(tight.path.size() * 200, cells.path.size()) << "pulled to a few corners per fold";
    ++checked;
  }
  EXPECT_GT(checked, 12);
}

TEST(PlannerModes, AnyAngleIsNoLongerThanThetaStar) {
  // Theta* (the reference in reference_any_angle.h) was this mode's search before the cell path pulled tight
  // with its corners slid replaced it, at 2-100x the time; its paths are the length to keep. On random maps
  // the pulled paths are shorter in sum (per pair either may win: neither is the shortest any-angle path).
  std::mt19937 rng(41);
  DijkstraPlanner planner;
  double theta = 0.0, pulled = 0.0;
  int pairs = 0;
  for (int trial = 0; trial < 8; ++trial) {
    RandomGrid g(&rng, 90, 90, 0.1 + 0.05 * (trial % 3), false);
    for (int q = 0; q < 6; ++q) {
      const Cell s = g.randomCell(&rng), t = g.randomCell(&rng);
      g.open(s);
      g.open(t);
      PlannerOptions o;
      o.any_angle = true;
      const auto tight = planner.plan(g.data.data(), g.data.size(), g.w, g.h, s, t, o);
      if (!tight.ok()) continue;
      expectClearPath(g, tight, s, t);
      theta += test::thetaStarLength(g.w, g.h, s, t, [&](int x, int y) { return g.free(x, y); });
      pulled += tight.cost;
      ++pairs;
    }
  }
  ASSERT_GT(pairs, 30);
  std::printf("any-angle: %d pairs, %.1f cells against Theta*'s %.1f\n", pairs, pulled, theta);
  EXPECT_LE(pulled, theta);
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
