// Dijkstra on an occupancy grid, with no ROS dependency: the ROS node, the pybind11 module and the cloud
// server all wrap this one core.
//
// Grid convention is nav_msgs/OccupancyGrid: int8, row-major (index y * width + x), -1 unknown, 0..100
// occupancy. Moves are 8-connected with cost 1 and sqrt(2); a diagonal move needs both orthogonal
// neighbours free (no corner cutting), the rules of the MovingAI benchmarks, so optimal lengths match
// theirs exactly.
//
// Options, all exact on their own graph: cost-aware planning (a move between cells a and b costs its
// length times the mean of w(a) and w(b), w = neutral_cost + cost_factor * occupancy, global_planner's
// model), inflation of a raw map by a robot and an inflation radius (inflation.h), A* with the octile
// heuristic (consistent, so its costs are Dijkstra's), and any-angle paths (the optimal cell path pulled
// tight along lines of sight that cross no blocked cell or corner and never raise the path's cost, its
// corners then slid to neighbouring cells while that lowers the cost). The
// options, their defaults and bounds are planner_options.h's.
#pragma once

#include <atomic>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <memory>
#include <string>
#include <vector>

#include "offload_planner_cpp/jump_point_search.h"
#include "offload_planner_cpp/plan_status.h"
#include "offload_planner_cpp/planner_options.h"

namespace offload_planner {

struct Cell {
  int x = 0;
  int y = 0;
  bool operator==(const Cell& other) const { return x == other.x && y == other.y; }
};

// The planner's one rule of which cells it may enter.
inline bool isPassable(std::int8_t occupancy, const PlannerOptions& options) {
  return occupancy < 0 ? !options.unknown_is_obstacle : occupancy < options.lethal_threshold;
}

// Whether the segment between the centres of cells a and b (both on the grid) crosses only passable cells
// and passes through no grid vertex beside a blocked cell: the line-of-sight rule of any-angle paths.
bool segmentClear(const std::int8_t* grid, int width, int height, Cell a, Cell b, const PlannerOptions& options);

struct PlanResult {
  PlanStatus status = PlanStatus::kOk;
  std::string message;       // human-readable reason when status != kOk
  std::vector<Cell> path;    // start to goal inclusive; empty unless kOk. Any-angle: the corners only
  double cost = 0.0;         // path length in cells
  double weighted_cost = 0.0;  // the path's cost in the model planned with (= cost when cost_factor is 0)
  Cell goal;                 // the cell actually reached (differs from the request within tolerance)
  std::uint64_t expansions = 0;  // cells settled
  double seconds = 0.0;      // wall time inside plan()
  const std::int8_t* grid = nullptr;  // the buffer planned on: bindings prove with it that nothing was copied
  bool ok() const { return status == PlanStatus::kOk; }
};

// Keeps its search buffers between calls so repeated plans on one map allocate nothing. Not thread
// safe: use one planner per thread.
class DijkstraPlanner {
 public:
  // `data` holds `size` cells of a width x height grid; `size` must equal width * height.
  PlanResult plan(const std::int8_t* data, std::size_t size, int width, int height, Cell start, Cell goal,
                  const PlannerOptions& options = PlannerOptions());

 private:
  // A bucket of Dial's queue: cell indices in an array grown before each level, so a push is a store and an
  // add, with no test of capacity and no branch on whether the move improved its cell.
  class Bucket {
   public:
    std::size_t size() const { return size_; }
    const int* data() const { return data_.get(); }
    int* end() { return data_.get() + size_; }
    void clear() { size_ = 0; }
    void setEnd(const int* end) { size_ = static_cast<std::size_t>(end - data_.get()); }
    // Room for `more` pushes beyond size().
    void reserveMore(std::size_t more);

   private:
    std::unique_ptr<int[]> data_;
    std::size_t size_ = 0;
    std::size_t capacity_ = 0;
  };
  // One wave of Dial's bucket queue (uniform cost). Its distances live in a padded buffer: the grid with a
  // frame of one blocked cell, row length stride_, where a blocked cell holds -inf. So the inner loop reads
  // no grid and tests no border: a blocked cell is never improved (nothing is below -inf), a settled one
  // neither (its distance is stored negated). Rows are derived from the grid as the wave reaches them, so a
  // search pays only for the rows it touches and never resets anything.
  struct Wave {
    double* dist;
    Bucket* buckets;
    std::size_t level = 0;    // the next level to settle: every cell nearer than that is settled
    int row_min = std::numeric_limits<int>::max();  // padded coordinates of the cells it settled
    int row_max = -1;
    int col_min = std::numeric_limits<int>::max();
    int col_max = -1;
    int derived_lo = 0;       // padded rows derived from the grid in this search
    int derived_hi = -1;
    int safe_begin = 0;       // padded indices whose rows within kDerivedMargin are derived
    int safe_end = 0;
    // Cells queued and not yet settled (stale duplicates included): the three buckets hold exactly those.
    std::size_t pending() const { return buckets[0].size() + buckets[1].size() + buckets[2].size(); }
  };
  // The distances of a finished search by cell index, from a wave's padded buffer or from dist_.
  struct Labels {
    const double* dist = nullptr;
    int width = 0;
    int stride = 0;           // 0: dist is indexed by cell; else a wave's padded buffer
    int row_lo = 0;           // padded rows the wave derived: outside them nothing was labelled
    int row_hi = -1;
    // A search that reopens cells (A* on buckets) may leave a cell unsettled whose label a rounding error
    // lowered after its neighbours took theirs from it: its trace also steps to unsettled labelled cells.
    bool trace_unsettled = false;
    double operator()(int cell) const {
      if (stride == 0) return dist[cell];
      const int y = cell / width;
      if (y + 1 < row_lo || y + 1 > row_hi) return std::numeric_limits<double>::infinity();
      return dist[(y + 1) * stride + (cell - y * width) + 1];
    }
  };
  enum class LevelEnd { kLevel, kTarget, kStopped };
  int padded(int cell) const { return (cell / width_ + 1) * stride_ + cell % width_ + 1; }
  int unpadded(int index) const { return (index / stride_ - 1) * width_ + index % stride_ - 1; }
  // Starts a bucket search's count; false, with cancelled_ set, when `cancel` is set already.
  bool beginWaves(const std::atomic<bool>* cancel);
  // Readies wave buffer `which` (0 forward, 1 backward) and starts a wave there from the cell `source`.
  Wave startWave(int which, Bucket* buckets, int source);
  // Derives padded rows [lo, hi] (clipped to the frame) of the wave's buffer from the grid, where not yet.
  void deriveRows(Wave& wave, int lo, int hi);
  Labels labels(const Wave& wave) const;
  // Settles the wave's current level; meet(i, j, d) sees every move i -> j offered at distance d by a cell
  // i = (x, y) with near(x, y) (padded indices and coordinates). Stops early when `target` is settled
  // (kTarget) or `cancel` was set (kStopped, cancelled_).
  template <class Near, class Meet>
  LevelEnd settleLevel(Wave& wave, int target, const std::atomic<bool>* cancel, Near near, Meet meet);
  // The rows a heap search settled cells in (and one beyond, where it relaxed), for the next beginSearch.
  void markDirtyRows(int row_min, int row_max);
  // Runs the search from `start`; returns true when `target` was settled. Sets cancelled_ and returns false
  // when `cancel` was set. Uniform cost, Dijkstra: Dial's buckets. Anything else: a binary heap.
  bool search(int start, int target, bool stop_at_target, const std::atomic<bool>* cancel);
  // Uniform-cost Dijkstra from both ends at once; true when they met: the optimal path crosses the move
  // meet_forward_ -> meet_backward_ and costs meeting_cost_.
  bool searchBidirectional(int start, int target, const std::atomic<bool>* cancel);
  bool searchHeap(int start, int target, bool stop_at_target, const std::atomic<bool>* cancel);
  // A* at uniform cost from start to target on a ring of eight buckets over the first wave's buffer (cells
  // reopened when improved); the labels in last_, the target's unsettled. True when the target was reached.
  bool searchBucketAStar(int start, int target, const std::atomic<bool>* cancel);
  // Best-first search over heap_ (lazy deletion), used by searchHeap: `estimate(j)` is the
  // heuristic, `relax(i, d, j, length)` offers j a cost through the settled cell i (at cost d) and returns
  // whether it improved dist_[j]. Checks `cancel` every `cancel_check` settled cells.
  template <class Estimate, class Relax>
  bool bestFirst(int start, int target, bool stop_at_target, const std::atomic<bool>* cancel,
                 std::uint64_t cancel_check, Estimate estimate, Relax relax);
  // Calls visit(j, length) for every legal 8-connected move out of cell i = (x, y), in a fixed order.
  template <class Visit>
  void forEachMove(int i, int x, int y, Visit visit) const;
  // The search kAuto runs for a plan from cell `from` to cell `target` (set per call: weighted_).
  Algorithm chooseAlgorithm(const PlannerOptions& options, int from, int target) const;
  // The free cell nearest to `goal` within `radius` cells (settled by the last search if
  // `settled_only`), ties to the first in row order; -1 if there is none.
  int nearestWithin(Cell goal, double radius, bool settled_only) const;
  // Walks back from `goal` to the source of the distances `labels` along settled cells, each step to the
  // neighbour with the smallest distance; the path runs from that source to `goal`.
  void tracePath(int goal, std::vector<Cell>* path, const Labels& labels) const;
  // tracePath over a wave's labels (uniform cost), in its padded buffer.
  void traceWave(int goal, std::vector<Cell>* path, const Labels& labels) const;
  // Pulls `path` tight along lines of sight that never raise its cost (corners are cells of the path).
  void pullTight(std::vector<Cell>* path) const;
  // Moves each corner of a pulled path to a neighbouring cell while that lowers its cost, and drops corners
  // whose neighbours see each other at no more cost (ends fixed).
  void refineCorners(std::vector<Cell>* path) const;
  // Cost of the segment between two cells (length times the weights it crosses), or +inf when not in sight.
  double segmentCost(int from, int to) const;
  // Cost of a path of corners, segment by segment.
  double pathCost(const std::vector<Cell>& path) const;
  bool passable(int index) const { return passable_[static_cast<std::uint8_t>(grid_[index])]; }
  double weight(int index) const { return weight_[static_cast<std::uint8_t>(grid_[index])]; }
  // A move's cost: its length times the mean weight of its two cells.
  double moveCost(int from, int to, double length) const {
    return weighted_ ? length * 0.5 * (weight(from) + weight(to)) : length;
  }
  double heuristic(int index) const;
  // A settled cell stores its distance negated (the start -0.0): `nd < dist` then never holds for it,
  // so relaxation needs no separate flag. These two read dist_, the heap searches' buffer.
  bool settled(int index) const { return std::signbit(dist_[index]); }
  double distance(int index) const { return std::fabs(dist_[index]); }
  // Readies dist_ (+inf everywhere); false, with cancelled_ set, when `cancel` came first.
  bool beginSearch(const std::atomic<bool>* cancel);

  // Set per call.
  const std::int8_t* grid_ = nullptr;
  int width_ = 0;
  int height_ = 0;
  bool passable_[256] = {};  // by occupancy value as uint8 (-1 unknown is 255)
  double weight_[256] = {};  // w by occupancy value, when weighted_
  bool weighted_ = false;
  bool astar_ = false;
  double min_weight_ = 1.0;  // the least w of any passable cell: scales the heuristic
  Cell target_cell_;
  std::uint64_t expansions_ = 0;
  bool cancelled_ = false;

  // Reused between calls: the heap searches' distances, +inf except in cells [dirty_begin_, dirty_end_), the
  // rows the last search touched, which the next search resets: a short search on a big map does not pay to
  // clear it all.
  std::vector<double> dist_;
  std::size_t dirty_begin_ = 0;
  std::size_t dirty_end_ = 0;
  // The bucket searches' padded buffers (forward and backward wave), allocated but never filled whole.
  int stride_ = 0;
  bool open_unknown_ = false;          // unknown cells passable (the grid rule of deriveRows)
  int lethal_ = 50;
  std::unique_ptr<double[]> wave_dist_[2];
  std::size_t wave_cells_[2] = {0, 0};
  Bucket buckets_[3];
  Bucket back_buckets_[3];
  Bucket astar_buckets_[8];
  Labels last_;                        // the last search's distances (the forward wave's)
  Labels backward_;                    // the last two-wave search's backward distances
  double meeting_cost_ = 0.0;
  int meet_forward_ = -1;
  int meet_backward_ = -1;
  bool start_component_settled_ = false;  // the last two-wave search's forward wave ran dry
  std::vector<std::pair<double, int>> heap_;
  std::vector<std::int8_t> inflated_;  // the grid after inflation, when asked for
  JumpPointSearch jump_;
};

}  // namespace offload_planner
