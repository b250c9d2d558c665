#include "offload_planner_cpp/dijkstra.h"

#include "offload_planner_cpp/inflation.h"
#include "best_first.h"
#include "segment_walk.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <sstream>
#include <utility>

namespace offload_planner {
namespace {

std::string cellText(Cell c) {
  std::ostringstream out;
  out << "(" << c.x << ", " << c.y << ")";
  return out.str();
}

}  // namespace

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

double DijkstraPlanner::heuristic(int index) const {
  if (!astar_) return 0.0;
  const int y = index / width_;
  const double dx = std::abs(index - y * width_ - target_cell_.x);
  const double dy = std::abs(y - target_cell_.y);
  // The octile distance is the shortest 8-connected length on an empty grid, and no move costs less than
  // its length times the least weight, so the heuristic never overestimates and is consistent.
  return min_weight_ * (std::max(dx, dy) + (kDiagonal - 1.0) * std::min(dx, dy));
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


void DijkstraPlanner::tracePath(int goal, std::vector<Cell>* path, const Labels& labels) const {
  if (labels.stride != 0) return traceWave(goal, path, labels);
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
  // A* at uniform cost to one cell: on buckets, as the waves.
  const bool bucket_astar = astar_ && !weighted_ && options.stop_at_goal && from != target;
  bool found = false;
  bool jumped = false;
  if (jump) {
    const JumpPointSearch::Outcome outcome = jump_.search(grid_, width, height, passable_, from, target, options.cancel);
    cancelled_ = outcome == JumpPointSearch::Outcome::kCancelled;
    found = jumped = outcome == JumpPointSearch::Outcome::kFound;
    result.expansions = jump_.expansions();
  } else {
    found = both_ends ? searchBidirectional(from, target, options.cancel)
            : bucket_astar ? searchBucketAStar(from, target, options.cancel)
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
    // The optimal cell path pulled tight, then its corners slid: never costlier than the cell path, and in
    // the time of a few lines of sight per corner (a Theta* search took 2-100x the cell search).
    pullTight(&result.path);
    refineCorners(&result.path);
  }
  if (weighted_ || options.any_angle) {
    // Length (and cost) of the path as returned: segments between its corners.
    double length = 0.0;
    double cost = 0.0;
    auto passableAt = [&](int i) { return passable(i); };
    for (std::size_t k = 1; k < result.path.size(); ++k) {
      const double dx = result.path[k].x - result.path[k - 1].x;
      const double dy = result.path[k].y - result.path[k - 1].y;
      length += std::sqrt(dx * dx + dy * dy);
      // At uniform cost a segment's cost is its length: no second walk (a tenth of a short any-angle plan).
      if (options.any_angle && weighted_) {
        walkSegment(result.path[k - 1], result.path[k], width, passableAt,
                    [&](int i, double part) { cost += part * weight(i); });
      }
    }
    result.cost = length;
    if (options.any_angle) result.weighted_cost = weighted_ ? cost : length;
  }
  result.goal = {reached % width, reached / width};
  return finish(PlanStatus::kOk, "");
}

}  // namespace offload_planner
