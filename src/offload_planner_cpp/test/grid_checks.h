// The uniform-cost search tests' grids and checks (test_jump_point_search, test_bucket_astar): a grid built from
// rows or filled at random, the oracle's cost on it (reference_search.h), and the legality of a returned path.
#pragma once

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

struct Grid {
  int w = 0, h = 0;
  std::vector<std::int8_t> data;
  Grid(int width, int height) : w(width), h(height), data(static_cast<std::size_t>(width) * height, 0) {}
  // Rows top to bottom: '.' free, '#' occupied (100), '?' unknown (-1).
  explicit Grid(const std::vector<std::string>& rows) : Grid(static_cast<int>(rows[0].size()), static_cast<int>(rows.size())) {
    for (int y = 0; y < h; ++y) {
      for (int x = 0; x < w; ++x) at(x, y) = rows[y][x] == '#' ? 100 : rows[y][x] == '?' ? -1 : 0;
    }
  }
  std::int8_t& at(int x, int y) { return data[static_cast<std::size_t>(y) * w + x]; }
  bool free(int x, int y, const PlannerOptions& o) const {
    return x >= 0 && y >= 0 && x < w && y < h && isPassable(data[static_cast<std::size_t>(y) * w + x], o);
  }
};

// The oracle at uniform cost.
inline double referenceCost(const Grid& g, Cell s, Cell t, const PlannerOptions& o) {
  return test::referenceCost(g.w, g.h, s, t, [&](int x, int y) { return g.free(x, y, o); },
                             [](int, int) { return 1.0; });
}

// Runs from s to t by legal moves only (no blocked cell, no diagonal past a blocked corner), and its steps
// add up to its cost.
inline void expectLegalPath(const Grid& g, const PlanResult& r, Cell s, Cell t, const PlannerOptions& o) {
  ASSERT_TRUE(r.ok()) << r.message;
  ASSERT_FALSE(r.path.empty());
  EXPECT_EQ(r.path.front(), s);
  EXPECT_EQ(r.path.back(), t);
  int straight = 0, diagonal = 0;
  for (std::size_t k = 0; k < r.path.size(); ++k) {
    const Cell c = r.path[k];
    ASSERT_TRUE(g.free(c.x, c.y, o)) << "cell " << k << " (" << c.x << ", " << c.y << ") is blocked";
    if (k == 0) continue;
    const Cell p = r.path[k - 1];
    const int dx = c.x - p.x, dy = c.y - p.y;
    ASSERT_TRUE(std::abs(dx) <= 1 && std::abs(dy) <= 1 && (dx != 0 || dy != 0)) << "step " << k << " is no move";
    if (dx != 0 && dy != 0) {
      ASSERT_TRUE(g.free(p.x + dx, p.y, o) && g.free(p.x, p.y + dy, o))
          << "step " << k << " from (" << p.x << ", " << p.y << ") cuts a corner";
      ++diagonal;
    } else {
      ++straight;
    }
  }
  EXPECT_NEAR(straight + std::sqrt(2.0) * diagonal, r.cost, 1e-9);
}

inline PlannerOptions with(Algorithm algorithm) {
  PlannerOptions o;
  o.algorithm = algorithm;
  return o;
}

inline PlanResult planOn(DijkstraPlanner& planner, const Grid& g, Cell s, Cell t, const PlannerOptions& o) {
  return planner.plan(g.data.data(), g.data.size(), g.w, g.h, s, t, o);
}

}  // namespace test
}  // namespace offload_planner
