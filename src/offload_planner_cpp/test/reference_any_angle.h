// The tests' any-angle oracles, written without the core's code: whether a segment between two cell centres
// meets a cell's closed square (so touching a blocked corner counts as crossing it), a line of sight from
// that, and a textbook Theta* over cell centres (Nash et al. 2007), the search the core's any-angle mode ran
// before it pulled the optimal cell path tight instead.
#pragma once

#include <algorithm>
#include <cmath>
#include <functional>
#include <queue>
#include <utility>
#include <vector>

#include "offload_planner_cpp/dijkstra.h"
#include "reference_search.h"

namespace offload_planner {
namespace test {

// Separating axes: the square's two axes and the segment's normal.
inline bool segmentMeetsCell(Cell a, Cell b, int cx, int cy) {
  const double ax = a.x + 0.5, ay = a.y + 0.5, bx = b.x + 0.5, by = b.y + 0.5;
  if (std::max(ax, bx) < cx || std::min(ax, bx) > cx + 1 || std::max(ay, by) < cy || std::min(ay, by) > cy + 1) {
    return false;
  }
  const double nx = by - ay, ny = ax - bx;  // normal of the segment
  double lo = INFINITY, hi = -INFINITY;
  for (int k = 0; k < 4; ++k) {
    const double px = cx + (k & 1), py = cy + (k >> 1);
    const double side = nx * (px - ax) + ny * (py - ay);
    lo = std::min(lo, side);
    hi = std::max(hi, side);
  }
  return lo <= 1e-12 && hi >= -1e-12;
}

// The first blocked cell the segment a-b meets, or {-1, -1}. free(x, y) is false off the grid.
template <class Free>
Cell firstBlockedOn(Cell a, Cell b, Free free) {
  for (int y = std::min(a.y, b.y) - 1; y <= std::max(a.y, b.y) + 1; ++y) {
    for (int x = std::min(a.x, b.x) - 1; x <= std::max(a.x, b.x) + 1; ++x) {
      if (segmentMeetsCell(a, b, x, y) && !free(x, y)) return {x, y};
    }
  }
  return {-1, -1};
}

// Theta*'s path length from s to t at uniform cost (+inf when unreachable): A* over the 8-connected moves
// (no diagonal past a blocked corner) where a cell may take its parent's parent when that one is in sight.
template <class Free>
double thetaStarLength(int width, int height, Cell s, Cell t, Free free) {
  const std::size_t n = static_cast<std::size_t>(width) * height;
  std::vector<double> g(n, INFINITY);
  std::vector<int> parent(n, -1);
  std::vector<char> closed(n, 0);
  auto cell = [&](int i) { return Cell{i % width, i / width}; };
  auto dist = [&](int i, int j) { return std::hypot(i % width - j % width, i / width - j / width); };
  auto sight = [&](int i, int j) { return firstBlockedOn(cell(i), cell(j), free).x < 0; };
  const int start = s.y * width + s.x, goal = t.y * width + t.x;
  using Item = std::pair<double, int>;
  std::priority_queue<Item, std::vector<Item>, std::greater<Item>> open;
  g[start] = 0;
  parent[start] = start;
  open.push({dist(start, goal), start});
  while (!open.empty()) {
    const int i = open.top().second;
    open.pop();
    if (closed[i]) continue;
    closed[i] = 1;
    if (i == goal) return g[i];
    forEachMove(width, i % width, i / width, free, [&](int, int, int j) {
      if (closed[j]) return;
      const int from = sight(parent[i], j) ? parent[i] : i;
      const double nd = g[from] + dist(from, j);
      if (nd < g[j]) {
        g[j] = nd;
        parent[j] = from;
        open.push({nd + dist(j, goal), j});
      }
    });
  }
  return INFINITY;
}

}  // namespace test
}  // namespace offload_planner
