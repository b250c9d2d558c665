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

const char* statusName(PlanStatus status) {
  switch (status) {
    case PlanStatus::kOk: return "ok";
    case PlanStatus::kEmptyMap: return "empty_map";
    case PlanStatus::kSizeMismatch: return "size_mismatch";
    case PlanStatus::kStartOffMap: return "start_off_map";
    case PlanStatus::kGoalOffMap: return "goal_off_map";
    case PlanStatus::kStartBlocked: return "start_blocked";
    case PlanStatus::kGoalBlocked: return "goal_blocked";
    case PlanStatus::kNoPath: return "no_path";
    case PlanStatus::kInvalidOptions: return "invalid_options";
  }
  return "unknown";
}

void DijkstraPlanner::buildFreeMap(const std::int8_t* data, const PlannerOptions& options) {
  const std::size_t cells = static_cast<std::size_t>(stride_) * static_cast<std::size_t>(height_ + 2);
  if (free_.size() != cells) {
    free_.assign(cells, 0);
    dist_.assign(cells, std::numeric_limits<double>::infinity());
    dirty_begin_ = dirty_end_ = 0;
  }
  const std::int8_t lethal = static_cast<std::int8_t>(std::min(options.lethal_threshold, 101));
  const std::uint8_t unknown = options.unknown_is_obstacle ? 0 : 1;
  for (int y = 0; y < height_; ++y) {
    const std::int8_t* in = data + static_cast<std::size_t>(y) * width_;
    std::uint8_t* out = free_.data() + static_cast<std::size_t>(y + 1) * stride_ + 1;
    for (int x = 0; x < width_; ++x) {  // branch-free so the compiler vectorises it
      out[x] = static_cast<std::uint8_t>(in[x] < 0 ? unknown : (in[x] < lethal ? 1 : 0));
    }
    out[-1] = out[width_] = 0;  // keep the padding blocked when the width changes
  }
}

void DijkstraPlanner::beginSearch() {
  std::fill(dist_.begin() + dirty_begin_, dist_.begin() + dirty_end_, std::numeric_limits<double>::infinity());
  dirty_begin_ = dirty_end_ = 0;
  for (auto& bucket : buckets_) bucket.clear();
  expansions_ = 0;
}

// Dial's bucket queue with bucket width 1, the smallest step cost (Dinitz): every cell in the lowest
// non-empty bucket already has its final distance, so buckets are settled in any order with O(1) queue
// work. Steps cost at most sqrt(2) < 2, so three buckets in a ring hold everything pending.
bool DijkstraPlanner::search(int start, int target, bool stop_at_target) {
  beginSearch();
  const int w = stride_;
  const std::uint8_t* const free = free_.data();
  double* const dist = dist_.data();
  int lowest = start;
  int highest = start;

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
      lowest = std::min(lowest, i);
      highest = std::max(highest, i);
      if (i == target) {
        reached = true;
        if (stop_at_target) {
          pending = 0;
          break;
        }
      }
      const bool fw = free[i - 1];
      const bool fe = free[i + 1];
      const bool fn = free[i - w];
      const bool fs = free[i + w];
      if (fw) relax(i - 1, d + 1.0);
      if (fe) relax(i + 1, d + 1.0);
      if (fn) relax(i - w, d + 1.0);
      if (fs) relax(i + w, d + 1.0);
      if (fn && fw && free[i - w - 1]) relax(i - w - 1, d + kDiagonal);
      if (fn && fe && free[i - w + 1]) relax(i - w + 1, d + kDiagonal);
      if (fs && fw && free[i + w - 1]) relax(i + w - 1, d + kDiagonal);
      if (fs && fe && free[i + w + 1]) relax(i + w + 1, d + kDiagonal);
    }
    pending -= std::min(pending, bucket.size());
    bucket.clear();
  }
  // Relaxed cells lie within one row of the settled ones.
  dirty_begin_ = static_cast<std::size_t>(lowest - w - 1);
  dirty_end_ = static_cast<std::size_t>(highest + w + 2);
  return reached;
}

void DijkstraPlanner::tracePath(int goal, std::vector<Cell>* path) const {
  const int w = stride_;
  const std::uint8_t* const free = free_.data();
  path->clear();
  int i = goal;
  path->push_back(cellAt(i));
  while (distance(i) > 0.0) {
    const bool fw = free[i - 1];
    const bool fe = free[i + 1];
    const bool fn = free[i - w];
    const bool fs = free[i + w];
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
    consider(fn && fw && free[i - w - 1], i - w - 1, kDiagonal);
    consider(fn && fe && free[i - w + 1], i - w + 1, kDiagonal);
    consider(fs && fw && free[i + w - 1], i + w - 1, kDiagonal);
    consider(fs && fe && free[i + w + 1], i + w + 1, kDiagonal);
    i = best;  // exists: a settled cell's predecessor on its shortest path is settled and closer
    path->push_back(cellAt(i));
  }
  std::reverse(path->begin(), path->end());
}

PlanResult DijkstraPlanner::plan(const std::int8_t* data, std::size_t size, int width, int height, Cell start,
                                 Cell goal, const PlannerOptions& options) {
  const auto started = std::chrono::steady_clock::now();
  PlanResult result;
  result.goal = goal;
  auto finish = [&](PlanStatus status, const std::string& message) {
    result.status = status;
    result.message = message;
    result.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count();
    return result;
  };

  if (width <= 0 || height <= 0 || size == 0 || data == nullptr) {
    std::ostringstream msg;
    msg << "empty map: " << width << " x " << height << " cells, " << size << " values";
    return finish(PlanStatus::kEmptyMap, msg.str());
  }
  if (static_cast<std::size_t>(width) * static_cast<std::size_t>(height) != size) {
    std::ostringstream msg;
    msg << "map size mismatch: " << width << " x " << height << " = "
        << static_cast<std::size_t>(width) * static_cast<std::size_t>(height) << " cells but " << size
        << " values";
    return finish(PlanStatus::kSizeMismatch, msg.str());
  }
  if (static_cast<std::size_t>(width + 2) * static_cast<std::size_t>(height + 2) >
      static_cast<std::size_t>(std::numeric_limits<int>::max())) {
    return finish(PlanStatus::kSizeMismatch, "map too large: more than 2^31 cells");
  }
  if (options.lethal_threshold < 1 || options.lethal_threshold > 101) {
    return finish(PlanStatus::kInvalidOptions,
                  "lethal_threshold must be in 1..101, got " + std::to_string(options.lethal_threshold));
  }
  if (!(options.goal_tolerance_cells >= 0.0) || !std::isfinite(options.goal_tolerance_cells)) {
    return finish(PlanStatus::kInvalidOptions, "goal tolerance must be a finite number >= 0");
  }

  width_ = width;
  height_ = height;
  stride_ = width + 2;
  buildFreeMap(data, options);
  const std::uint8_t* const free = free_.data();

  auto on_map = [&](Cell c) { return c.x >= 0 && c.y >= 0 && c.x < width && c.y < height; };
  const std::string size_text = std::to_string(width) + " x " + std::to_string(height);
  if (!on_map(start)) return finish(PlanStatus::kStartOffMap, "start " + cellText(start) + " is off the " + size_text + " map");
  if (!on_map(goal)) return finish(PlanStatus::kGoalOffMap, "goal " + cellText(goal) + " is off the " + size_text + " map");
  if (!free[index(start)]) {
    return finish(PlanStatus::kStartBlocked, "start " + cellText(start) + " is in an obstacle (occupancy " +
                                                 std::to_string(data[start.y * width + start.x]) + ")");
  }

  // Goal candidates, nearest to the requested goal first: the goal itself if free, then free cells
  // within the tolerance.
  std::vector<std::pair<double, int>> candidates;
  if (free[index(goal)]) candidates.emplace_back(0.0, index(goal));
  const double radius = options.goal_tolerance_cells;
  if (radius > 0.0) {
    const int r = static_cast<int>(std::floor(radius));
    for (int y = std::max(0, goal.y - r); y <= std::min(height - 1, goal.y + r); ++y) {
      for (int x = std::max(0, goal.x - r); x <= std::min(width - 1, goal.x + r); ++x) {
        const double d = std::hypot(x - goal.x, y - goal.y);
        const int i = index({x, y});
        if (d > 0.0 && d <= radius && free[i]) candidates.emplace_back(d, i);
      }
    }
    std::stable_sort(candidates.begin(), candidates.end(),
                     [](const auto& a, const auto& b) { return a.first < b.first; });
  }
  if (candidates.empty()) {
    std::ostringstream msg;
    msg << "goal " << cellText(goal) << " is in an obstacle (occupancy " << static_cast<int>(data[goal.y * width + goal.x])
        << ")";
    if (radius > 0.0) msg << " and no free cell lies within " << radius << " cells of it";
    return finish(PlanStatus::kGoalBlocked, msg.str());
  }

  // One search suffices: if the nearest candidate is not reached, the search has exhausted the start's
  // component, so the first settled candidate is the nearest reachable one.
  int reached = -1;
  if (search(index(start), candidates.front().second, options.stop_at_goal)) {
    reached = candidates.front().second;
  } else {
    for (const auto& candidate : candidates) {
      if (settled(candidate.second)) {
        reached = candidate.second;
        break;
      }
    }
  }
  result.expansions = expansions_;
  if (reached < 0) {
    std::string msg = "goal " + cellText(goal) + " is unreachable from start " + cellText(start);
    if (radius > 0.0) msg += ", and so is every free cell within the tolerance";
    return finish(PlanStatus::kNoPath, msg);
  }
  tracePath(reached, &result.path);
  result.cost = distance(reached);
  result.goal = cellAt(reached);
  return finish(PlanStatus::kOk, "");
}

}  // namespace offload_planner
