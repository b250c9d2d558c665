#include "offload_planner_cpp/dijkstra.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <sstream>

namespace offload_planner {
namespace {

constexpr double kDiagonal = 1.4142135623730951;  // sqrt(2)

std::string cellText(Cell c) {
  std::ostringstream out;
  out << "(" << c.x << ", " << c.y << ")";
  return out.str();
}

}  // namespace

void DijkstraPlanner::beginSearch() {
  constexpr double kUnseen = std::numeric_limits<double>::infinity();
  const std::size_t cells = static_cast<std::size_t>(width_) * static_cast<std::size_t>(height_);
  if (dist_.size() != cells) {
    dist_.assign(cells, kUnseen);
  } else if (dirty_end_ > dirty_begin_) {
    std::fill(dist_.begin() + dirty_begin_, dist_.begin() + dirty_end_, kUnseen);
  }
  dirty_begin_ = dirty_end_ = 0;
  for (auto& bucket : buckets_) bucket.clear();
  expansions_ = 0;
}

// Dial's bucket queue with bucket width 1, the smallest step cost (Dinitz): every cell in the lowest
// non-empty bucket already has its final distance, so buckets are settled in any order with O(1) queue
// work. Steps cost at most sqrt(2) < 2, so three buckets in a ring hold everything pending.
bool DijkstraPlanner::search(int start, int target, bool stop_at_target, const std::atomic<bool>* cancel) {
  beginSearch();
  // Checked once every kCancelCheck settled cells: a relaxed load costs nothing at that rate, and even a
  // slow robot settles that many cells in well under a millisecond.
  constexpr std::uint64_t kCancelCheck = 4096;
  cancelled_ = cancel != nullptr && cancel->load(std::memory_order_relaxed);
  if (cancelled_) return false;
  const int w = width_;
  const int h = height_;
  double* const dist = dist_.data();
  int row_min = h;
  int row_max = -1;

  dist[start] = 0.0;
  buckets_[0].push_back(start);
  std::size_t pending = 1;
  bool reached = false;

  auto relax = [&](int j, double nd) {
    if (nd < dist[j]) {  // false for settled cells, whose stored distance is negative
      dist[j] = nd;
      buckets_[static_cast<std::size_t>(nd) % 3].push_back(j);
      ++pending;
    }
  };

  for (std::size_t level = 0; pending > 0; ++level) {
    std::vector<int>& bucket = buckets_[level % 3];
    // Relaxations from this bucket land in the next two, never in this one (steps cost >= 1).
    for (std::size_t k = 0; k < bucket.size(); ++k) {
      const int i = bucket[k];
      const double d = dist[i];
      if (std::signbit(d)) continue;  // stale duplicate of an improved entry
      dist[i] = -d;
      ++expansions_;
      if (cancel != nullptr && expansions_ % kCancelCheck == 0 && cancel->load(std::memory_order_relaxed)) {
        cancelled_ = true;
        pending = 0;
        break;
      }
      const int y = i / w;
      const int x = i - y * w;
      row_min = std::min(row_min, y);
      row_max = std::max(row_max, y);
      if (i == target) {
        reached = true;
        if (stop_at_target) {
          pending = 0;
          break;
        }
      }
      const bool fw = x > 0 && passable(i - 1);
      const bool fe = x < w - 1 && passable(i + 1);
      const bool fn = y > 0 && passable(i - w);
      const bool fs = y < h - 1 && passable(i + w);
      if (fw) relax(i - 1, d + 1.0);
      if (fe) relax(i + 1, d + 1.0);
      if (fn) relax(i - w, d + 1.0);
      if (fs) relax(i + w, d + 1.0);
      if (fn && fw && passable(i - w - 1)) relax(i - w - 1, d + kDiagonal);
      if (fn && fe && passable(i - w + 1)) relax(i - w + 1, d + kDiagonal);
      if (fs && fw && passable(i + w - 1)) relax(i + w - 1, d + kDiagonal);
      if (fs && fe && passable(i + w + 1)) relax(i + w + 1, d + kDiagonal);
    }
    pending -= std::min(pending, bucket.size());
    bucket.clear();
  }
  // Relaxed cells lie at most one row beyond the settled ones.
  dirty_begin_ = static_cast<std::size_t>(std::max(0, row_min - 1)) * w;
  dirty_end_ = static_cast<std::size_t>(std::min(h, row_max + 2)) * w;
  return reached;
}

void DijkstraPlanner::tracePath(int goal, std::vector<Cell>* path) const {
  const int w = width_;
  const int h = height_;
  path->clear();
  int i = goal;
  path->push_back({i % w, i / w});
  while (distance(i) > 0.0) {
    const int y = i / w;
    const int x = i - y * w;
    const bool fw = x > 0 && passable(i - 1);
    const bool fe = x < w - 1 && passable(i + 1);
    const bool fn = y > 0 && passable(i - w);
    const bool fs = y < h - 1 && passable(i + w);
    int best = -1;
    double best_dist = std::numeric_limits<double>::infinity();
    auto consider = [&](bool legal, int j, double step) {
      if (legal && settled(j) && distance(j) + step < best_dist) {
        best_dist = distance(j) + step;
        best = j;
      }
    };
    consider(fw, i - 1, 1.0);
    consider(fe, i + 1, 1.0);
    consider(fn, i - w, 1.0);
    consider(fs, i + w, 1.0);
    consider(fn && fw && passable(i - w - 1), i - w - 1, kDiagonal);
    consider(fn && fe && passable(i - w + 1), i - w + 1, kDiagonal);
    consider(fs && fw && passable(i + w - 1), i + w - 1, kDiagonal);
    consider(fs && fe && passable(i + w + 1), i + w + 1, kDiagonal);
    i = best;  // exists: a settled cell's predecessor on its shortest path is settled and closer
    path->push_back({i % w, i / w});
  }
  std::reverse(path->begin(), path->end());
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
      if (d2 < best_d2 && static_cast<double>(d2) <= limit && passable(i) && (!settled_only || settled(i))) {
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
  if (static_cast<std::size_t>(width) * static_cast<std::size_t>(height) >
      static_cast<std::size_t>(std::numeric_limits<int>::max())) {
    return finish(PlanStatus::kInvalidMap, "map too large: more than 2^31 cells");
  }
  if (options.lethal_threshold < 1 || options.lethal_threshold > 101) {
    return finish(PlanStatus::kInvalidRequest,
                  "lethal_threshold must be in 1..101, got " + std::to_string(options.lethal_threshold));
  }
  if (!(options.goal_tolerance_cells >= 0.0) || !std::isfinite(options.goal_tolerance_cells)) {
    return finish(PlanStatus::kInvalidRequest, "goal tolerance must be a finite number >= 0");
  }

  grid_ = data;
  width_ = width;
  height_ = height;
  for (int v = -128; v < 128; ++v) {
    passable_[static_cast<std::uint8_t>(v)] = isPassable(static_cast<std::int8_t>(v), options);
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
  const bool found = search(index(start), target, options.stop_at_goal, options.cancel);
  result.expansions = expansions_;
  if (cancelled_) {
    return finish(PlanStatus::kCancelled, "cancelled by the caller after " + std::to_string(expansions_) +
                                              " expansions");
  }
  if (!found) reached = radius > 0.0 ? nearestWithin(goal, radius, true) : -1;
  if (reached < 0) {
    std::string msg = "goal " + cellText(goal) + " is unreachable from start " + cellText(start);
    if (radius > 0.0) msg += ", and so is every free cell within the tolerance";
    return finish(PlanStatus::kNoPath, msg);
  }
  tracePath(reached, &result.path);
  result.cost = distance(reached);
  result.goal = {reached % width, reached / width};
  return finish(PlanStatus::kOk, "");
}

}  // namespace offload_planner
