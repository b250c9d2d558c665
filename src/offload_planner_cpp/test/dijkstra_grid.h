// The text grids of the core planner's tests: rows as text, the textbook reference cost and the legal-path
// check (test_dijkstra, test_dijkstra_waves).
#ifndef OFFLOAD_PLANNER_CPP_TEST_DIJKSTRA_GRID_H
#define OFFLOAD_PLANNER_CPP_TEST_DIJKSTRA_GRID_H

#include <gtest/gtest.h>

#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <string>
#include <vector>

#include "offload_planner_cpp/dijkstra.h"
#include "reference_search.h"

namespace offload_planner {
namespace test {

const double kSqrt2 = std::sqrt(2.0);

// These tests are of the Dijkstra waves: their options ask for them (the default, kAuto, may take jump points).
struct DijkstraOptions : PlannerOptions {
  DijkstraOptions() { algorithm = Algorithm::kDijkstra; }
};

// Rows top to bottom as text: '.' free, '#' occupied (100), '?' unknown (-1), digits d -> 10 * d.
struct Grid {
  int width = 0, height = 0;
  std::vector<std::int8_t> data;
  explicit Grid(const std::vector<std::string>& rows) {
    height = static_cast<int>(rows.size());
    width = static_cast<int>(rows[0].size());
    for (const auto& row : rows) {
      for (char c : row) {
        data.push_back(c == '#' ? 100 : c == '?' ? -1 : c == '.' ? 0 : static_cast<std::int8_t>(10 * (c - '0')));
      }
    }
  }
  PlanResult plan(Cell s, Cell g, const PlannerOptions& o = DijkstraOptions()) {
    return planner.plan(data.data(), data.size(), width, height, s, g, o);
  }
  DijkstraPlanner planner;
};

// Independent reference (reference_search.h): textbook Dijkstra with a binary heap, same move rules.
inline double referenceCost(const std::vector<std::int8_t>& grid, int w, int h, Cell s, Cell g) {
  auto free = [&](int x, int y) { return x >= 0 && y >= 0 && x < w && y < h && grid[y * w + x] == 0; };
  return offload_planner::test::referenceCost(w, h, s, g, free, [](int, int) { return 1.0; });
}

// Each step of a path is one legal move and the steps add up to the reported cost.
inline void expectValidPath(const Grid& grid, const PlanResult& r, Cell s, Cell g) {
  ASSERT_TRUE(r.ok()) << r.message;
  ASSERT_FALSE(r.path.empty());
  EXPECT_EQ(r.path.front(), s);
  EXPECT_EQ(r.path.back(), g);
  double length = 0;
  auto freeAt = [&](int x, int y) { return grid.data[y * grid.width + x] < 50 && grid.data[y * grid.width + x] >= 0; };
  for (std::size_t k = 1; k < r.path.size(); ++k) {
    const int dx = r.path[k].x - r.path[k - 1].x, dy = r.path[k].y - r.path[k - 1].y;
    ASSERT_LE(std::abs(dx), 1);
    ASSERT_LE(std::abs(dy), 1);
    ASSERT_TRUE(dx != 0 || dy != 0);
    ASSERT_TRUE(freeAt(r.path[k].x, r.path[k].y));
    if (dx != 0 && dy != 0) {
      ASSERT_TRUE(freeAt(r.path[k - 1].x + dx, r.path[k - 1].y)) << "corner cut at step " << k;
      ASSERT_TRUE(freeAt(r.path[k - 1].x, r.path[k - 1].y + dy)) << "corner cut at step " << k;
    }
    length += (dx != 0 && dy != 0) ? kSqrt2 : 1.0;
  }
  EXPECT_NEAR(length, r.cost, 1e-9);
}

}  // namespace test
}  // namespace offload_planner

#endif  // OFFLOAD_PLANNER_CPP_TEST_DIJKSTRA_GRID_H
