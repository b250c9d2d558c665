#include "offload_planner_cpp/dijkstra.h"

#include "offload_planner_cpp/inflation.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <sstream>
#include <utility>

namespace offload_planner {
namespace {

constexpr double kDiagonal = 1.4142135623730951;  // sqrt(2)

std::string cellText(Cell c) {
  std::ostringstream out;
  out << "(" << c.x << ", " << c.y << ")";
  return out.str();
}

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
  const double length = std::hypot(static_cast<double>(dx), static_cast<double>(dy));
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

}  // namespace

bool segmentClear(const std::int8_t* grid, int width, int height, Cell a, Cell b, const PlannerOptions& options) {
  auto on = [&](Cell c) { return c.x >= 0 && c.y >= 0 && c.x < width && c.y < height; };
  if (!on(a) || !on(b) || !isPassable(grid[static_cast<std::size_t>(a.y) * width + a.x], options)) return false;
  return walkSegment(a, b, width, [&](int i) { return isPassable(grid[i], options); }, [](int, double) {});
}

bool DijkstraPlanner::beginSearch(const std::atomic<bool>* cancel) {
  constexpr double kUnseen = std::numeric_limits<double>::infinity();
  // A first plan on a big map fills 8 bytes per cell (200 MB on 5000 x 5000), seconds of page faults in a
  // cold VM: the fill goes a chunk at a time and stops at a cancel, leaving the buffer short, so the next
  // search fills it again.
  constexpr std::size_t kFillChunk = std::size_t{1} << 20;
  auto cancelled = [&] { return cancel != nullptr && cancel->load(std::memory_order_relaxed); };
  const std::size_t cells = static_cast<std::size_t>(width_) * static_cast<std::size_t>(height_);
  expansions_ = 0;
  cancelled_ = false;
  if (dist_.size() != cells) {
    dist_.clear();
    dist_.reserve(cells);
    while (dist_.size() < cells && !(cancelled_ = cancelled())) {
      dist_.insert(dist_.end(), std::min(kFillChunk, cells - dist_.size()), kUnseen);
    }
  } else if (dirty_end_ > dirty_begin_) {
    std::fill(dist_.begin() + dirty_begin_, dist_.begin() + dirty_end_, kUnseen);
  }
  // A buffer of full size is clean now; one left short is filled whole next time.
  dirty_begin_ = dirty_end_ = 0;
  cancelled_ = cancelled_ || cancelled();
  return !cancelled_;
}

void DijkstraPlanner::markDirtyRows(int row_min, int row_max) {
  // Relaxed cells lie at most one row beyond the settled ones.
  dirty_begin_ = static_cast<std::size_t>(std::max(0, row_min - 1)) * width_;
  dirty_end_ = static_cast<std::size_t>(std::min(height_, row_max + 2)) * width_;
}

template <class Visit>
inline void DijkstraPlanner::forEachMove(int i, int x, int y, Visit visit) const {
  const int w = width_;
  const bool fw = x > 0 && passable(i - 1);
  const bool fe = x < w - 1 && passable(i + 1);
  const bool fn = y > 0 && passable(i - w);
  const bool fs = y < height_ - 1 && passable(i + w);
  if (fw) visit(i - 1, 1.0);
  if (fe) visit(i + 1, 1.0);
  if (fn) visit(i - w, 1.0);
  if (fs) visit(i + w, 1.0);
  if (fn && fw && passable(i - w - 1)) visit(i - w - 1, kDiagonal);
  if (fn && fe && passable(i - w + 1)) visit(i - w + 1, kDiagonal);
  if (fs && fw && passable(i + w - 1)) visit(i + w - 1, kDiagonal);
  if (fs && fe && passable(i + w + 1)) visit(i + w + 1, kDiagonal);
}

double DijkstraPlanner::heuristic(int index) const {
  if (!astar_) return 0.0;
  const int y = index / width_;
  const double dx = std::abs(index - y * width_ - target_cell_.x);
  const double dy = std::abs(y - target_cell_.y);
  // The octile distance is the shortest 8-connected length on an empty grid, and no move costs less than
  // its length times the least weight, so the heuristic never overestimates and is consistent.
  return min_weight_ * (std::max(dx, dy) + (kDiagonal - 1.0) * std::min(dx, dy));
}

template <class Estimate, class Relax>
bool DijkstraPlanner::bestFirst(int start, int target, bool stop_at_target, const std::atomic<bool>* cancel,
                                std::uint64_t cancel_check, Estimate estimate, Relax relax) {
  if (!beginSearch(cancel)) return false;
  const int w = width_;
  const int h = height_;
  double* const dist = dist_.data();
  int row_min = h;
  int row_max = -1;
  heap_.clear();
  auto later = [](const std::pair<double, int>& a, const std::pair<double, int>& b) { return a.first > b.first; };
  dist[start] = 0.0;
  heap_.emplace_back(estimate(start), start);
  bool reached = false;
  while (!heap_.empty()) {
    std::pop_heap(heap_.begin(), heap_.end(), later);
    const int i = heap_.back().second;
    heap_.pop_back();
    const double d = dist[i];
    if (std::signbit(d)) continue;  // stale entry of a settled cell
    dist[i] = -d;
    ++expansions_;
    if (cancel != nullptr && expansions_ % cancel_check == 0 && cancel->load(std::memory_order_relaxed)) {
      cancelled_ = true;
      break;
    }
    const int y = i / w;
    const int x = i - y * w;
    row_min = std::min(row_min, y);
    row_max = std::max(row_max, y);
    if (i == target) {
      reached = true;
      if (stop_at_target) break;
    }
    forEachMove(i, x, y, [&](int j, double length) {
      if (relax(i, d, j, length)) {
        heap_.emplace_back(dist[j] + estimate(j), j);
        std::push_heap(heap_.begin(), heap_.end(), later);
      }
    });
  }
  markDirtyRows(row_min, row_max);
  return reached;
}

// Dijkstra or A*, with a heap: for weighted moves, where buckets of width one would not hold, and for A*.
bool DijkstraPlanner::searchHeap(int start, int target, bool stop_at_target, const std::atomic<bool>* cancel) {
  // dist_ is read through the member: bestFirst's beginSearch may reallocate it.
  const bool reached = bestFirst(start, target, stop_at_target, cancel, 4096, [&](int j) { return heuristic(j); },
                   [&](int i, double d, int j, double length) {
                     const double nd = d + moveCost(i, j, length);
                     if (!(nd < dist_[j])) return false;  // always false for settled cells (negative)
                     dist_[j] = nd;
                     return true;
                   });
  last_ = Labels{dist_.data(), width_};
  return reached;
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

void DijkstraPlanner::tracePath(int goal, std::vector<Cell>* path, const Labels& labels) const {
  const int w = width_;
  path->clear();
  int i = goal;
  path->push_back({i % w, i / w});
  while (std::fabs(labels(i)) > 0.0) {
    const int y = i / w;
    int best = -1;
    double best_dist = std::numeric_limits<double>::infinity();
    forEachMove(i, i - y * w, y, [&](int j, double length) {
      const double label = labels(j);
      if (!std::signbit(label)) return;  // not settled
      const double through = std::fabs(label) + moveCost(j, i, length);
      if (through < best_dist) {
        best_dist = through;
        best = j;
      }
    });
    i = best;  // exists: a settled cell's predecessor on its shortest path is settled and closer
    path->push_back({i % w, i / w});
  }
  std::reverse(path->begin(), path->end());
}

Algorithm DijkstraPlanner::chooseAlgorithm(const PlannerOptions& options, int from, int target) const {
  if (weighted_ || !options.stop_at_goal || from == target) return Algorithm::kDijkstra;
  // Jump point search pays where runs of free cells are long: its cost is the jump points it queues, and a
  // jump point comes with every free cell beside a blocked one. So it counts free/blocked boundaries per
  // free cell (rho) on runs of cells sampled from rows around the two ends. Measured, time of the two waves over jump point
  // search: random maps at rho 0.2, 0.4, 0.5, 0.6, 0.7, 0.8, 1.0 (1000 x 1000, random pairs) 3.2, 3.2,
  // 1.8, 1.4, 1.2, 1.0, 0.8; corner to corner on 2000 x 2000 at rho 0.8: 0.4; maze512-1-0 (rho 2.0) 0.2;
  // 8room_000 (0.55) 1.8; every ROS map (0.02-0.23) 3.3-5.8. Below 0.6 it is jump point search.
  constexpr double kMaxBoundariesPerFreeCell = 0.6;
  // At most 32 rows of 4 runs of 32 cells: a few microseconds, whatever the distance.
  constexpr int kSampledRows = 32;
  constexpr int kRunsPerRow = 4;
  constexpr int kRunCells = 32;
  const int w = width_;
  const int fx = from % w, fy = from / w, tx = target % w, ty = target / w;
  const int margin = std::max(std::abs(fx - tx), std::abs(fy - ty)) / 4 + 8;
  const int x0 = std::max(0, std::min(fx, tx) - margin);
  const int x1 = std::min(w - 1, std::max(fx, tx) + margin);
  const int y0 = std::max(0, std::min(fy, ty) - margin);
  const int y1 = std::min(height_ - 1, std::max(fy, ty) + margin);
  const int rows = std::min(kSampledRows, y1 - y0 + 1);
  const int span = x1 - x0 + 1;
  const int runs = span <= kRunsPerRow * kRunCells ? 1 : kRunsPerRow;
  const int run_cells = runs == 1 ? span : kRunCells;
  std::size_t free = 0;
  std::size_t boundaries = 0;
  for (int k = 0; k < rows; ++k) {
    const int y = y0 + (rows > 1 ? static_cast<int>(static_cast<long long>(k) * (y1 - y0) / (rows - 1)) : 0);
    const std::int8_t* const row = grid_ + static_cast<std::size_t>(y) * w;
    const std::int8_t* const below = y + 1 < height_ ? row + w : row;  // the last row: no boundary below
    for (int r = 0; r < runs; ++r) {
      const int begin = x0 + (runs > 1 ? r * (span - run_cells) / (runs - 1) : 0);
      bool left = passable(y * w + begin);
      for (int x = begin; x < begin + run_cells; ++x) {
        const bool here = passable_[static_cast<std::uint8_t>(row[x])];
        free += here;
        boundaries += (here != left) + (here != passable_[static_cast<std::uint8_t>(below[x])]);
        left = here;
      }
    }
  }
  return static_cast<double>(boundaries) < kMaxBoundariesPerFreeCell * static_cast<double>(free) ? Algorithm::kJps
                                                                                              : Algorithm::kDijkstra;
}

int DijkstraPlanner::nearestWithin(Cell goal, double radius, bool settled_only) const {
  // Row-major scan of the disc; a strictly smaller distance replaces the best, so ties go to the first
  // cell in row order. Squared integer distances keep it exact and cheap.
  const long long r = static_cast<long long>(std::floor(radius));
  const double limit = radius * radius;
  const long long y_end = std::min<long long>(height_ - 1, goal.y + r);
  const long long x_begin = std::max<long long>(0, goal.x - r);
  const long long x_end = std::min<long long>(width_ - 1, goal.x + r);
  int best = -1;
  long long best_d2 = std::numeric_limits<long long>::max();
  for (long long y = std::max<long long>(0, goal.y - r); y <= y_end; ++y) {
    for (long long x = x_begin; x <= x_end; ++x) {
      const long long d2 = (x - goal.x) * (x - goal.x) + (y - goal.y) * (y - goal.y);
      const int i = static_cast<int>(y * width_ + x);
      if (d2 < best_d2 && static_cast<double>(d2) <= limit && passable(i) && (!settled_only || std::signbit(last_(i)))) {
        best = i;
        best_d2 = d2;
      }
    }
  }
  return best;
}

PlanResult DijkstraPlanner::plan(const std::int8_t* data, std::size_t size, int width, int height, Cell start,
                                 Cell goal, const PlannerOptions& options) {
  const auto started = std::chrono::steady_clock::now();
  PlanResult result;
  result.goal = goal;
  result.grid = data;
  auto finish = [&](PlanStatus status, const std::string& message) {
    result.status = status;
    result.message = message;
    result.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count();
    return result;
  };

  if (width <= 0 || height <= 0 || size == 0 || data == nullptr) {
    std::ostringstream msg;
    msg << "empty map: " << width << " x " << height << " cells, " << size << " values";
    return finish(PlanStatus::kInvalidMap, msg.str());
  }
  if (static_cast<std::size_t>(width) * static_cast<std::size_t>(height) != size) {
    std::ostringstream msg;
    msg << "map size mismatch: " << width << " x " << height << " = "
        << static_cast<std::size_t>(width) * static_cast<std::size_t>(height) << " cells but " << size
        << " values";
    return finish(PlanStatus::kInvalidMap, msg.str());
  }
  // Indices are ints, in the grid and in the waves' buffers (the grid with a frame of one cell).
  if ((static_cast<std::size_t>(width) + 2) * (static_cast<std::size_t>(height) + 2) >
      static_cast<std::size_t>(std::numeric_limits<int>::max())) {
    std::ostringstream msg;
    msg << "map too large: " << width << " x " << height
        << " cells and a frame of one cell around them are more than 2^31 - 1, the planner's index range";
    return finish(PlanStatus::kInvalidMap, msg.str());
  }
  const std::string options_problem = optionsProblem(options);
  if (!options_problem.empty()) return finish(PlanStatus::kInvalidRequest, options_problem);

  if (options.robot_radius_cells > 0.0 || options.inflation_radius_cells > 0.0) {
    inflate(data, width, height, options, &inflated_);
    data = inflated_.data();
  }
  grid_ = data;
  width_ = width;
  height_ = height;
  stride_ = width + 2;
  lethal_ = options.lethal_threshold;
  open_unknown_ = !options.unknown_is_obstacle;
  weighted_ = options.cost_factor > 0.0;
  min_weight_ = weighted_ ? options.neutral_cost : 1.0;
  for (int v = -128; v < 128; ++v) {
    passable_[static_cast<std::uint8_t>(v)] = isPassable(static_cast<std::int8_t>(v), options);
    weight_[static_cast<std::uint8_t>(v)] = options.neutral_cost + options.cost_factor * std::max(v, 0);
  }

  auto on_map = [&](Cell c) { return c.x >= 0 && c.y >= 0 && c.x < width && c.y < height; };
  auto index = [&](Cell c) { return c.y * width + c.x; };
  const std::string size_text = std::to_string(width) + " x " + std::to_string(height);
  if (!on_map(start)) return finish(PlanStatus::kStartOffMap, "start " + cellText(start) + " is off the " + size_text + " map");
  if (!on_map(goal)) return finish(PlanStatus::kGoalOffMap, "goal " + cellText(goal) + " is off the " + size_text + " map");
  if (!passable(index(start))) {
    return finish(PlanStatus::kStartBlocked, "start " + cellText(start) + " is in an obstacle (occupancy " +
                                                 std::to_string(data[index(start)]) + ")");
  }

  // The tolerance only matters when the goal itself is blocked or unreachable: a free, reachable goal
  // costs no scan of its surroundings. A radius beyond the map's diagonal covers the whole map anyway.
  const double radius = std::min(options.goal_tolerance_cells, std::hypot(width, height));
  int target = index(goal);
  if (!passable(target)) {
    target = radius > 0.0 ? nearestWithin(goal, radius, false) : -1;
    if (target < 0) {
      std::ostringstream msg;
      msg << "goal " << cellText(goal) << " is in an obstacle (occupancy " << static_cast<int>(data[index(goal)])
          << ")";
      if (radius > 0.0) msg << " and no free cell lies within " << options.goal_tolerance_cells << " cells of it";
      return finish(PlanStatus::kGoalBlocked, msg.str());
    }
  }

  // One search suffices: `target` is the free cell nearest the goal, so if it is reached it is the
  // answer; if not, the search has exhausted the start's component and the nearest settled cell within
  // the tolerance is the nearest reachable one.
  int reached = target;
  target_cell_ = {target % width, target / width};
  const int from = index(start);
  const Algorithm algorithm = options.algorithm == Algorithm::kAuto ? chooseAlgorithm(options, from, target)
                                                                    : options.algorithm;
  astar_ = algorithm == Algorithm::kAStar;
  // Jump point search goes from one cell to another (uniform cost: plan() refuses jps with cost_factor > 0).
  const bool jump = algorithm == Algorithm::kJps && options.stop_at_goal && from != target;
  // Uniform-cost Dijkstra to one cell runs from both ends: two waves of half the radius settle about half
  // the cells of one on open ground. It proves an unreachable goal as soon as either wave runs dry.
  const bool both_ends = !jump && !weighted_ && !astar_ && options.stop_at_goal && from != target;
  bool found = false;
  bool jumped = false;
  if (jump) {
    const JumpPointSearch::Outcome outcome = jump_.search(grid_, width, height, passable_, from, target, options.cancel);
    cancelled_ = outcome == JumpPointSearch::Outcome::kCancelled;
    found = jumped = outcome == JumpPointSearch::Outcome::kFound;
    result.expansions = jump_.expansions();
  } else {
    found = both_ends ? searchBidirectional(from, target, options.cancel)
            : weighted_ || astar_ ? searchHeap(from, target, options.stop_at_goal, options.cancel)
                                  : search(from, target, options.stop_at_goal, options.cancel);
    result.expansions = expansions_;
  }
  const bool met = both_ends && found;
  if (!found && !cancelled_ && radius > 0.0 && (jump || (both_ends && !start_component_settled_))) {
    // The nearest reachable cell within the tolerance needs the start's whole component settled: the
    // goal's wave ran dry first (or jump points settle no area), so one wave settles the rest of it now.
    found = search(from, target, true, options.cancel);
    result.expansions += expansions_;
  }
  if (cancelled_) {
    return finish(PlanStatus::kCancelled, "cancelled by the caller after " + std::to_string(result.expansions) +
                                              " expansions");
  }
  if (!found) reached = radius > 0.0 ? nearestWithin(goal, radius, true) : -1;
  if (reached < 0) {
    std::string msg = "goal " + cellText(goal) + " is unreachable from start " + cellText(start);
    if (radius > 0.0) msg += ", and so is every free cell within the tolerance";
    return finish(PlanStatus::kNoPath, msg);
  }
  if (jumped) {
    result.path.clear();
    for (int i : jump_.path()) result.path.push_back({i % width, i / width});
    result.cost = result.weighted_cost =
        static_cast<double>(jump_.straight()) + kDiagonal * static_cast<double>(jump_.diagonal());
  } else if (met) {
    // Start to the meeting move on the forward wave, then on to the target on the backward one.
    tracePath(meet_forward_, &result.path, last_);
    std::vector<Cell> tail;
    tracePath(meet_backward_, &tail, backward_);
    result.path.insert(result.path.end(), tail.rbegin(), tail.rend());
    result.cost = result.weighted_cost = meeting_cost_;
  } else {
    tracePath(reached, &result.path, last_);
    result.cost = weighted_ ? 0.0 : std::fabs(last_(reached));
    result.weighted_cost = std::fabs(last_(reached));
  }
  if (options.any_angle) {
    // Two candidates, the cheaper wins: the optimal cell path pulled tight (never costlier than it), and
    // Theta*'s path (usually shorter: its corners need not be cells of one cell path) pulled tight too.
    pullTight(&result.path);
    const double pulled = pathCost(result.path);
    std::vector<Cell> theta;
    const std::uint64_t settled = result.expansions;
    if (searchTheta(index(start), reached, options.cancel, &theta)) {
      pullTight(&theta);
      if (pathCost(theta) < pulled) result.path.swap(theta);
    }
    result.expansions = settled + expansions_;
    if (cancelled_) {
      return finish(PlanStatus::kCancelled, "cancelled by the caller after " + std::to_string(result.expansions) +
                                                " expansions");
    }
  }
  if (weighted_ || options.any_angle) {
    // Length (and cost) of the path as returned: segments between its corners.
    double length = 0.0;
    double cost = 0.0;
    auto passableAt = [&](int i) { return passable(i); };
    for (std::size_t k = 1; k < result.path.size(); ++k) {
      length += std::hypot(result.path[k].x - result.path[k - 1].x, result.path[k].y - result.path[k - 1].y);
      if (options.any_angle) {
        walkSegment(result.path[k - 1], result.path[k], width, passableAt,
                    [&](int i, double part) { cost += weighted_ ? part * weight(i) : part; });
      }
    }
    result.cost = length;
    if (options.any_angle) result.weighted_cost = cost;
  }
  result.goal = {reached % width, reached / width};
  return finish(PlanStatus::kOk, "");
}

}  // namespace offload_planner
