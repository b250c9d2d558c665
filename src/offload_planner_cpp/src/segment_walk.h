// The one walk along a straight segment between two cell centres, shared by the any-angle search (any_angle.cpp)
// and the final check of every path (dijkstra.cpp). Internal to the core: not installed.
#ifndef OFFLOAD_PLANNER_CPP_SEGMENT_WALK_H
#define OFFLOAD_PLANNER_CPP_SEGMENT_WALK_H

#include "offload_planner_cpp/dijkstra.h"

#include <cmath>
#include <cstdlib>

namespace offload_planner {
namespace detail {

// Walks the segment between the centres of cells a and b (Amanatides and Woo), calling
// visit(index, length in cells inside that cell) for every cell it crosses. Returns false as soon as it
// would enter a blocked cell, or pass through a grid vertex beside a blocked cell (the corner rule of the
// 8-connected moves). Crossings are decided in integers, so a segment through a vertex is seen exactly.
template <class Passable, class Visit>
bool walkSegment(Cell a, Cell b, int width, Passable passable, Visit visit) {
  const long long dx = std::llabs(static_cast<long long>(b.x) - a.x);
  const long long dy = std::llabs(static_cast<long long>(b.y) - a.y);
  const int sx = b.x > a.x ? 1 : -1;
  const int sy = b.y > a.y ? 1 : -1;
  // Exact squares, one rounding (and no libm call, which a walk that only looks would still pay).
  const double length = std::sqrt(static_cast<double>(dx * dx + dy * dy));
  // The k-th vertical boundary is crossed at t = (2k + 1) / (2 dx), the k-th horizontal at (2k + 1) / (2 dy).
  long long kx = 0;
  long long ky = 0;
  int x = a.x;
  int y = a.y;
  double t = 0.0;
  auto at = [&](int cx, int cy) { return static_cast<int>(static_cast<long long>(cy) * width + cx); };
  while (kx < dx || ky < dy) {
    // Compare (2kx + 1) / dx with (2ky + 1) / dy without division.
    const long long lhs = kx < dx ? (2 * kx + 1) * dy : -1;
    const long long rhs = ky < dy ? (2 * ky + 1) * dx : -1;
    double next;
    if (ky >= dy || (kx < dx && lhs < rhs)) {
      next = (2.0 * kx + 1.0) / (2.0 * dx);
      visit(at(x, y), (next - t) * length);
      x += sx;
      ++kx;
    } else if (kx >= dx || rhs < lhs) {
      next = (2.0 * ky + 1.0) / (2.0 * dy);
      visit(at(x, y), (next - t) * length);
      y += sy;
      ++ky;
    } else {  // through a vertex: the two cells beside it are only touched, and must be free
      next = (2.0 * kx + 1.0) / (2.0 * dx);
      visit(at(x, y), (next - t) * length);
      if (!passable(at(x + sx, y)) || !passable(at(x, y + sy))) return false;
      x += sx;
      y += sy;
      ++kx;
      ++ky;
    }
    t = next;
    if (!passable(at(x, y))) return false;
  }
  visit(at(x, y), (1.0 - t) * length);
  return true;
}

// walkSegment's verdict for a unit move from a to b (an 8-connected path's step), without its arithmetic: the end
// cell and, on a diagonal, the two cells beside the vertex it passes (the corner rule above). a itself is not
// looked at (the walk's caller checks the first cell). test_path_check holds the two equal on random walks.
template <class Passable>
bool unitMoveClear(Cell a, Cell b, int width, Passable passable) {
  auto at = [&](int cx, int cy) { return static_cast<int>(static_cast<long long>(cy) * width + cx); };
  return passable(at(b.x, b.y)) && (a.x == b.x || a.y == b.y || (passable(at(b.x, a.y)) && passable(at(a.x, b.y))));
}

}  // namespace detail
using detail::unitMoveClear;
using detail::walkSegment;
}  // namespace offload_planner

#endif  // OFFLOAD_PLANNER_CPP_SEGMENT_WALK_H
