// The tests' oracle: a textbook Dijkstra with a binary heap over the core's moves (8-connected, 1 and sqrt(2),
// no diagonal past a blocked corner), written without the core's code. A move from i to j costs its length
// times weight(i, j); free(x, y) says whether a cell may be entered (and must be false off the grid).
#pragma once

#include <cmath>
#include <functional>
#include <queue>
#include <utility>
#include <vector>

#include "offload_planner_cpp/dijkstra.h"

namespace offload_planner {
namespace test {

// Calls move(dx, dy, j) for each of the core's moves out of cell i = (x, y): a free neighbour (j its index), and
// no diagonal past a blocked corner.
template <class Free, class Move>
void forEachMove(int width, int x, int y, Free free, Move move) {
  for (int dy = -1; dy <= 1; ++dy) {
    for (int dx = -1; dx <= 1; ++dx) {
      if ((dx == 0 && dy == 0) || !free(x + dx, y + dy)) continue;
      if (dx != 0 && dy != 0 && (!free(x + dx, y) || !free(x, y + dy))) continue;
      move(dx, dy, (y + dy) * width + x + dx);
    }
  }
}

template <class Free, class Weight>
double referenceCost(int width, int height, Cell s, Cell t, Free free, Weight weight) {
  const double sqrt2 = std::sqrt(2.0);
  std::vector<double> dist(static_cast<std::size_t>(width) * height, INFINITY);
  using Item = std::pair<double, int>;
  std::priority_queue<Item, std::vector<Item>, std::greater<Item>> heap;
  dist[s.y * width + s.x] = 0;
  heap.push({0, s.y * width + s.x});
  while (!heap.empty()) {
    auto [d, i] = heap.top();
    heap.pop();
    if (d > dist[i]) continue;
    // (a structured binding is not captured by reference before C++20)
    forEachMove(width, i % width, i / width, free, [&, d = d, i = i](int dx, int dy, int j) {
      const double nd = d + ((dx != 0 && dy != 0) ? sqrt2 : 1.0) * weight(i, j);
      if (nd < dist[j]) {
        dist[j] = nd;
        heap.push({nd, j});
      }
    });
  }
  return dist[t.y * width + t.x];
}

}  // namespace test
}  // namespace offload_planner
