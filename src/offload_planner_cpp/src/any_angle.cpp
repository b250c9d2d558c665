// Any-angle paths (options.any_angle): string pulling of the optimal cell path (pullTight), its corners slid
// to cheaper cells (refineCorners), and the costs of straight segments they compare (segmentCost, pathCost); segmentClear for callers
// that check a segment of their own (the binding's path_clear).
#include "offload_planner_cpp/dijkstra.h"

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

namespace {

// pullTight at uniform cost on a path of long straight runs (corridors): false, doing nothing, on any other.
// The cells of one straight run of moves see each other (the path's own moves keep to free cells and pass no
// blocked corner: the line-of-sight rule), so the far cell is sought among the path's turns first, galloping
// then bisecting, and then by bisection within the one run where sight ends. Galloping over every cell walked
// each run of a folded corridor about a dozen times (any-angle took 1.8x the jump points' time on the 4-cell
// serpentine, 1.3x this way, the same paths). Where runs are short the two ways can stop at different cells
// (sight along a path is not monotone): on street and random maps this way's paths were up to 0.2 % longer.
template <class Fits>
bool pullTightByTurns(const std::vector<Cell>& path, Fits fits, std::vector<Cell>* pulled) {
  constexpr std::size_t kLongRun = 256;  // cells per run on average
  const std::size_t n = path.size();
  auto turns_at = [&](std::size_t k) {
    return path[k].x - path[k - 1].x != path[k + 1].x - path[k].x || path[k].y - path[k - 1].y != path[k + 1].y - path[k].y;
  };
  std::vector<std::size_t> turns;
  for (std::size_t k = 1; k + 1 < n; ++k) {
    if (turns_at(k)) turns.push_back(k);
  }
  turns.push_back(n - 1);
  if (n < kLongRun * turns.size()) return false;
  std::size_t anchor = 0;
  std::size_t next = 0;  // the first turn after the anchor: the end of the anchor's own run
  while (anchor + 1 < n) {
    while (turns[next] <= anchor) ++next;
    std::size_t good = next;
    std::size_t bad = turns.size();
    for (std::size_t step = 1; good + 1 < turns.size(); step *= 2) {
      const std::size_t t = std::min(good + step, turns.size() - 1);
      if (!fits(anchor, turns[t])) {
        bad = t;
        break;
      }
      good = t;
    }
    while (bad < turns.size() && bad - good > 1) {
      const std::size_t mid = good + (bad - good) / 2;
      (fits(anchor, turns[mid]) ? good : bad) = mid;
    }
    std::size_t far = turns[good];
    if (bad < turns.size()) {
      std::size_t beyond = turns[bad];  // the cells between are one straight run
      while (beyond - far > 1) {
        const std::size_t mid = far + (beyond - far) / 2;
        (fits(anchor, mid) ? far : beyond) = mid;
      }
    }
    pulled->push_back(path[far]);
    anchor = far;
  }
  return true;
}

}  // namespace

void DijkstraPlanner::pullTight(std::vector<Cell>* path) const {
  const std::size_t n = path->size();
  if (n < 3) return;
  const int w = width_;
  auto index = [&](Cell c) { return c.y * w + c.x; };
  // The cost of the path up to each cell, in the same model as a segment's (a move is half in each cell);
  // at uniform cost a segment in sight never costs more than the cells it replaces, and only sight is walked.
  std::vector<double> prefix(weighted_ ? n : 0, 0.0);
  for (std::size_t k = 1; k < prefix.size(); ++k) {
    prefix[k] = prefix[k - 1] + segmentCost(index((*path)[k - 1]), index((*path)[k]));
  }
  auto passableAt = [&](int i) { return passable(i); };
  std::vector<Cell> pulled{path->front()};
  std::size_t anchor = 0;
  // Cell k may follow the anchor when it is in sight and the segment costs no more than the cells it replaces.
  // At uniform cost, sight alone. Walked from the far end (sight is symmetric): a segment that fails mostly
  // fails near it, where the path turns out of sight, so the walk stops early instead of crossing the run first.
  auto in_sight = [&](std::size_t from, std::size_t k) {
    return walkSegment((*path)[k], (*path)[from], w, passableAt, [](int, double) {});
  };
  if (!weighted_ && pullTightByTurns(*path, in_sight, &pulled)) {
    path->swap(pulled);
    return;
  }
  auto fits = [&](std::size_t k) {
    if (!weighted_) return in_sight(anchor, k);
    const double cost = segmentCost(index((*path)[anchor]), index((*path)[k]));
    return cost <= prefix[k] - prefix[anchor] + 1e-9 * prefix[k];
  };
  while (anchor + 1 < n) {
    // Galloping, then bisection, for a far cell that fits: O(log run) lines of sight per corner, where trying
    // every cell of a long straight run was quadratic in its length. Every corner taken is checked.
    std::size_t good = anchor + 1;
    std::size_t bad = n;
    for (std::size_t step = 1; good + 1 < n; step *= 2) {
      const std::size_t k = std::min(good + step, n - 1);
      if (!fits(k)) {
        bad = k;
        break;
      }
      good = k;
    }
    while (bad < n && bad - good > 1) {
      const std::size_t mid = good + (bad - good) / 2;
      (fits(mid) ? good : bad) = mid;
    }
    pulled.push_back((*path)[good]);
    anchor = good;
  }
  path->swap(pulled);
}

void DijkstraPlanner::refineCorners(std::vector<Cell>* path) const {
  std::vector<Cell>& p = *path;
  if (p.size() < 3) return;
  const int w = width_;
  auto index = [&](Cell c) { return c.y * w + c.x; };
  auto passableAt = [&](int i) { return passable(i); };
  // sqrt of the exact integer sum, correctly rounded: std::hypot, a libm call, was a ninth of an any-angle
  // plan's time on lak303d.
  auto length = [](Cell a, Cell b) {
    const double dx = a.x - b.x;
    const double dy = a.y - b.y;
    return std::sqrt(dx * dx + dy * dy);
  };
  auto cost = [&](Cell a, Cell b) {
    if (weighted_) return segmentCost(index(a), index(b));
    return walkSegment(a, b, w, passableAt, [](int, double) {}) ? length(a, b) : std::numeric_limits<double>::infinity();
  };
  // seg[k]: the cost of the segment from corner k to corner k + 1; dirty[k]: corner k may still improve.
  std::vector<double> seg(p.size() - 1);
  for (std::size_t k = 0; k + 1 < p.size(); ++k) seg[k] = cost(p[k], p[k + 1]);
  std::vector<char> dirty(p.size(), 1);
  // Every change lowers the cost by more than a rounding error, so this ends; the cap bounds the time.
  for (int pass = 0, changed = 1; changed && pass < 64; ++pass) {
    changed = 0;
    for (std::size_t k = 1; k + 1 < p.size(); ++k) {
      if (!dirty[k]) continue;
      dirty[k] = 0;
      const double now = seg[k - 1] + seg[k];
      const double slack = 1e-12 * now;
      // A corner whose neighbours see each other at no more cost goes.
      const double direct = cost(p[k - 1], p[k + 1]);
      if (direct <= now) {
        p.erase(p.begin() + static_cast<std::ptrdiff_t>(k));
        seg.erase(seg.begin() + static_cast<std::ptrdiff_t>(k));
        dirty.erase(dirty.begin() + static_cast<std::ptrdiff_t>(k));
        seg[k - 1] = direct;
        dirty[k - 1] = dirty[k] = 1;
        changed = 1;
        --k;
        continue;
      }
      // Else it moves to the neighbouring cell that lowers the cost most, if any: corners drift towards the
      // obstacle corners they turn around, which cell-path corners only approximate.
      double best = now - slack;
      Cell to = p[k];
      double to_in = 0.0, to_out = 0.0;
      for (int dy = -1; dy <= 1; ++dy) {
        for (int dx = -1; dx <= 1; ++dx) {
          const Cell c{p[k].x + dx, p[k].y + dy};
          if ((dx == 0 && dy == 0) || c.x < 0 || c.y < 0 || c.x >= w || c.y >= height_ || !passable(index(c))) continue;
          // No segment costs less than its length times the least weight: most candidates end here unwalked.
          if (!(min_weight_ * (length(p[k - 1], c) + length(c, p[k + 1])) < best)) continue;
          // Walked from the moved corner (sight is symmetric), where a blocked segment mostly meets its wall.
          const double in = weighted_ ? cost(p[k - 1], c) : cost(c, p[k - 1]);
          if (!(in < best)) continue;
          const double out = cost(c, p[k + 1]);
          if (in + out < best) {
            best = in + out;
            to = c;
            to_in = in;
            to_out = out;
          }
        }
      }
      if (to == p[k]) continue;
      p[k] = to;
      seg[k - 1] = to_in;
      seg[k] = to_out;
      dirty[k - 1] = dirty[k] = dirty[k + 1] = 1;
      changed = 1;
    }
  }
}

}  // namespace offload_planner
