// Any-angle paths (options.any_angle): Theta* over the grid (searchTheta), string pulling of a grid path
// (pullTight), and the costs of straight segments they compare (segmentCost, pathCost); segmentClear for callers
// that check a segment of their own (the binding's path_clear).
#include "offload_planner_cpp/dijkstra.h"

#include "best_first.h"
#include "segment_walk.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <vector>

namespace offload_planner {

bool segmentClear(const std::int8_t* grid, int width, int height, Cell a, Cell b, const PlannerOptions& options) {
  auto on = [&](Cell c) { return c.x >= 0 && c.y >= 0 && c.x < width && c.y < height; };
  if (!on(a) || !on(b) || !isPassable(grid[static_cast<std::size_t>(a.y) * width + a.x], options)) return false;
  return walkSegment(a, b, width, [&](int i) { return isPassable(grid[i], options); }, [](int, double) {});
}

double DijkstraPlanner::segmentCost(int from, int to) const {
  const int w = width_;
  double cost = 0.0;
  const bool visible = walkSegment({from % w, from / w}, {to % w, to / w}, w, [&](int i) { return passable(i); },
                                   [&](int i, double length) { cost += weighted_ ? length * weight(i) : length; });
  return visible ? cost : std::numeric_limits<double>::infinity();
}

double DijkstraPlanner::pathCost(const std::vector<Cell>& path) const {
  double cost = 0.0;
  for (std::size_t k = 1; k < path.size(); ++k) {
    cost += segmentCost(path[k - 1].y * width_ + path[k - 1].x, path[k].y * width_ + path[k].x);
  }
  return cost;
}

bool DijkstraPlanner::searchTheta(int start, int target, const std::atomic<bool>* cancel, std::vector<Cell>* path) {
  const int w = width_;
  const std::size_t cells = static_cast<std::size_t>(w) * static_cast<std::size_t>(height_);
  if (parent_.size() != cells) parent_.assign(cells, -1);
  parent_[start] = start;   // parents are only read for settled cells
  const Cell goal{target % w, target / w};
  // Euclidean distance times the least weight: no segment costs less, so the heuristic is consistent.
  auto euclid = [&](int i) { return min_weight_ * std::hypot(i % w - goal.x, i / w - goal.y); };
  auto relax = [&](int i, double d, int j, double length) {
    if (settled(j)) return false;
    // Path 2 of Theta*: straight from i's parent when j is in its sight; else path 1, through i.
    double best = d + moveCost(i, j, length);
    int from = i;
    const int up = parent_[i];
    if (up != i) {
      const double straight = distance(up) + segmentCost(up, j);
      if (straight <= best) {
        best = straight;
        from = up;
      }
    }
    if (!(best < dist_[j])) return false;
    dist_[j] = best;
    parent_[j] = from;
    return true;
  };
  if (!bestFirst(start, target, true, cancel, 1024, euclid, relax)) return false;
  path->clear();
  for (int i = target;; i = parent_[i]) {
    path->push_back({i % w, i / w});
    if (i == start) break;
  }
  std::reverse(path->begin(), path->end());
  return true;
}

void DijkstraPlanner::pullTight(std::vector<Cell>* path) const {
  const std::size_t n = path->size();
  if (n < 3) return;
  const int w = width_;
  auto index = [&](Cell c) { return c.y * w + c.x; };
  // The cost of the path up to each corner, in the same model as a segment's (a move is half in each cell).
  std::vector<double> prefix(n, 0.0);
  for (std::size_t k = 1; k < n; ++k) prefix[k] = prefix[k - 1] + segmentCost(index((*path)[k - 1]), index((*path)[k]));
  auto passableAt = [&](int i) { return passable(i); };
  std::vector<Cell> pulled{path->front()};
  std::size_t anchor = 0;
  while (anchor + 1 < n) {
    std::size_t best = anchor + 1;
    for (std::size_t k = anchor + 2; k < n; ++k) {
      double cost = 0.0;
      const bool visible = walkSegment((*path)[anchor], (*path)[k], w, passableAt,
                                       [&](int i, double length) { cost += weighted_ ? length * weight(i) : length; });
      if (!visible) break;
      // The straight segment must not cost more than the cells it replaces (it never does at uniform cost).
      if (cost <= prefix[k] - prefix[anchor] + 1e-9 * prefix[k]) best = k;
    }
    pulled.push_back((*path)[best]);
    anchor = best;
  }
  path->swap(pulled);
}

}  // namespace offload_planner
