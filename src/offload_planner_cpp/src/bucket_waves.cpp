// The default's uniform-cost search: Dial's bucket queue in waves over padded distance buffers, from one end
// (search) or from both (searchBidirectional). See dijkstra.h for the buffers and the README for why.
#include "offload_planner_cpp/dijkstra.h"
#include "diagonal_step.h"

#include <algorithm>
#include <cmath>
#include <limits>

namespace offload_planner {

void DijkstraPlanner::Bucket::reserveMore(std::size_t more) {
  if (size_ + more <= capacity_) return;
  const std::size_t capacity = std::max(size_ + more, 2 * capacity_);
  std::unique_ptr<int[]> grown(new int[capacity]);
  std::copy(data_.get(), data_.get() + size_, grown.get());
  data_.swap(grown);
  capacity_ = capacity;
}

// A wave keeps the rows within this many of every cell it settled derived: a settled cell reads its own
// neighbours' rows, and the other wave's meeting test reads up to three rows beyond its settled box.
constexpr int kDerivedMargin = 3;
// Rows derived at a time beyond the one that needed them.
constexpr int kDeriveAhead = 16;

void DijkstraPlanner::deriveRows(Wave& wave, int lo, int hi) {
  constexpr double kBlocked = -std::numeric_limits<double>::infinity();
  constexpr double kUnseen = std::numeric_limits<double>::infinity();
  lo = std::max(lo, 0);
  hi = std::min(hi, height_ + 1);
  const int w = width_;
  const int lethal = lethal_;
  const bool open_unknown = open_unknown_;
  auto derive = [&](int row) {
    double* const out = wave.dist + static_cast<std::size_t>(row) * stride_;
    if (row == 0 || row == height_ + 1) {
      std::fill(out, out + stride_, kBlocked);
      return;
    }
    const std::int8_t* const cells = grid_ + static_cast<std::size_t>(row - 1) * w;
    out[0] = out[w + 1] = kBlocked;
    // isPassable, written so the compiler can vectorise it (isPassable itself in this loop is 5 % slower on
    // the Husky playpen's plans, which derive most of their rows).
    for (int x = 0; x < w; ++x) {
      const int v = cells[x];
      out[x + 1] = ((v >= 0) & (v < lethal)) | ((v < 0) & open_unknown) ? kUnseen : kBlocked;
    }
  };
  if (wave.derived_hi < wave.derived_lo) {
    for (int row = lo; row <= hi; ++row) derive(row);
    wave.derived_lo = lo;
    wave.derived_hi = hi;
  } else {
    for (int row = lo; row < wave.derived_lo; ++row) derive(row);
    for (int row = wave.derived_hi + 1; row <= hi; ++row) derive(row);
    wave.derived_lo = std::min(wave.derived_lo, lo);
    wave.derived_hi = std::max(wave.derived_hi, hi);
  }
  // At the frame there is nothing further to derive.
  wave.safe_begin = wave.derived_lo == 0 ? 0 : (wave.derived_lo + kDerivedMargin) * stride_;
  wave.safe_end = wave.derived_hi == height_ + 1 ? (height_ + 2) * stride_
                                                  : (wave.derived_hi + 1 - kDerivedMargin) * stride_;
}

// Dial's bucket queue with bucket width 1, the smallest step cost (Dinitz): every cell in the lowest
// non-empty bucket already has its final distance, so buckets are settled in any order with O(1) queue
// work. Steps cost at most sqrt(2) < 2, so three buckets in a ring hold everything pending.
template <class Near, class Meet>
DijkstraPlanner::LevelEnd DijkstraPlanner::settleLevel(Wave& wave, int target, const std::atomic<bool>* cancel,
                                                       Near near, Meet meet) {
  constexpr std::uint64_t kCancelCheck = 4096;  // a relaxed load costs nothing at that rate
  constexpr double kBlocked = -std::numeric_limits<double>::infinity();
  Bucket* const buckets = wave.buckets;
  const Bucket& bucket = buckets[wave.level % 3];
  const std::size_t entries = bucket.size();
  // Relaxations from this level land in the next two, never in this one (steps cost >= 1): an orthogonal
  // move always in the next, a diagonal one in the next or the one after. At most eight per entry.
  Bucket& next = buckets[(wave.level + 1) % 3];
  Bucket& after = buckets[(wave.level + 2) % 3];
  next.reserveMore(8 * entries);
  after.reserveMore(8 * entries);
  int* next_end = next.end();
  int* after_end = after.end();
  const double after_level = static_cast<double>(wave.level + 2);
  // The wave's counters live in locals while the level runs: stores through dist could alias the
  // members, which would keep the compiler from holding them in registers.
  double* const dist = wave.dist;
  const int s = stride_;
  std::uint64_t expansions = expansions_;
  int row_min = wave.row_min;
  int row_max = wave.row_max;
  int col_min = wave.col_min;
  int col_max = wave.col_max;
  int safe_begin = wave.safe_begin;
  int safe_end = wave.safe_end;
  LevelEnd end = LevelEnd::kLevel;
  // The search waits on memory, not arithmetic: a level's cells are scattered along the wave's front, each
  // on three rows of its own. The bucket says which cells come next, so their rows are fetched ahead.
  constexpr std::size_t kPrefetchAhead = 8;
  const int* const entry = bucket.data();
  for (std::size_t k = 0; k < entries; ++k) {
    const int i = entry[k];
    if (k + kPrefetchAhead < entries) {
      const int ahead = entry[k + kPrefetchAhead];
      __builtin_prefetch(dist + ahead - s, 1);
      __builtin_prefetch(dist + ahead, 1);
      __builtin_prefetch(dist + ahead + s, 1);
    }
    const double d = dist[i];
    if (std::signbit(d)) continue;  // stale duplicate of an improved entry
    dist[i] = -d;
    ++expansions;
    if (cancel != nullptr && expansions % kCancelCheck == 0 && cancel->load(std::memory_order_relaxed)) {
      cancelled_ = true;
      end = LevelEnd::kStopped;
      break;
    }
    const int y = i / s;
    const int x = i - y * s;
    if (i < safe_begin || i >= safe_end) {
      deriveRows(wave, y - kDeriveAhead, y + kDeriveAhead);
      safe_begin = wave.safe_begin;
      safe_end = wave.safe_end;
    }
    row_min = std::min(row_min, y);
    row_max = std::max(row_max, y);
    col_min = std::min(col_min, x);
    col_max = std::max(col_max, x);
    if (i == target) {
      end = LevelEnd::kTarget;
      break;
    }
    const double d1 = d + 1.0;
    const double d2 = d + kDiagonal;
    const bool fw = dist[i - 1] != kBlocked;
    const bool fe = dist[i + 1] != kBlocked;
    const bool fn = dist[i - s] != kBlocked;
    const bool fs = dist[i + s] != kBlocked;
    // A diagonal move lands in the bucket after next when it crosses that level.
    const bool diagonal_after = d2 >= after_level;
    // Only a cell near the other wave can offer a crossing: elsewhere the moves skip looking at it.
    if (near(x, y)) {
      auto offer = [&](int j, double nd, bool legal) {
        const double old = dist[j];
        // A cell this wave has settled gains nothing, and offers no crossing the proof needs (those run
        // from a cell settled here to one not yet settled here). Nor does a blocked one (-inf).
        if (!legal || std::signbit(old)) return;
        meet(i, j, nd);
        if (nd < old) {
          dist[j] = nd;
          if (nd < after_level) *next_end++ = j; else *after_end++ = j;
        }
      };
      // forEachMove's order, which the meeting's ties follow.
      offer(i - 1, d1, true);
      offer(i + 1, d1, true);
      offer(i - s, d1, true);
      offer(i + s, d1, true);
      offer(i - s - 1, d2, fn && fw);
      offer(i - s + 1, d2, fn && fe);
      offer(i + s - 1, d2, fs && fw);
      offer(i + s + 1, d2, fs && fe);
      continue;
    }
    // Elsewhere without a branch on each move's outcome: on a cluttered map whether a move is legal, and
    // whether it improves its cell, is a coin toss, and a mispredicted branch costs more than the store.
    auto relax = [&](int j, double nd, bool legal, int*& out) {
      const double old = dist[j];
      const bool better = legal & (nd < old);   // false for settled (negative) and blocked (-inf) cells
      dist[j] = better ? nd : old;
      *out = j;
      out += better;
    };
    relax(i - 1, d1, true, next_end);
    relax(i + 1, d1, true, next_end);
    relax(i - s, d1, true, next_end);
    relax(i + s, d1, true, next_end);
    int* out = diagonal_after ? after_end : next_end;
    relax(i - s - 1, d2, fn & fw, out);
    relax(i - s + 1, d2, fn & fe, out);
    relax(i + s - 1, d2, fs & fw, out);
    relax(i + s + 1, d2, fs & fe, out);
    after_end = diagonal_after ? out : after_end;
    next_end = diagonal_after ? next_end : out;
  }
  next.setEnd(next_end);
  after.setEnd(after_end);
  expansions_ = expansions;
  wave.row_min = row_min;
  wave.row_max = row_max;
  wave.col_min = col_min;
  wave.col_max = col_max;
  if (end != LevelEnd::kLevel) return end;
  buckets[wave.level % 3].clear();
  ++wave.level;
  return LevelEnd::kLevel;
}

DijkstraPlanner::Wave DijkstraPlanner::startWave(int which, Bucket* buckets, int source) {
  // Allocated, never filled: deriveRows writes each row before the wave reads it.
  const std::size_t cells = static_cast<std::size_t>(stride_) * static_cast<std::size_t>(height_ + 2);
  if (wave_cells_[which] != cells) {
    wave_dist_[which].reset();  // the old buffer goes before the new one comes
    wave_dist_[which].reset(new double[cells]);
    wave_cells_[which] = cells;
  }
  for (int k = 0; k < 3; ++k) buckets[k].clear();
  Wave wave{wave_dist_[which].get(), buckets};
  const int p = padded(source);
  const int y = p / stride_;
  deriveRows(wave, y - kDeriveAhead, y + kDeriveAhead);
  wave.dist[p] = 0.0;
  // The source is in the box even if the wave never settles it (the other wave may finish first).
  wave.row_min = wave.row_max = y;
  wave.col_min = wave.col_max = p % stride_;
  buckets[0].reserveMore(1);
  *buckets[0].end() = p;
  buckets[0].setEnd(buckets[0].end() + 1);
  return wave;
}

void DijkstraPlanner::traceWave(int goal, std::vector<Cell>* path, const Labels& labels) const {
  // tracePath's walk in the wave's padded buffer: neighbours at fixed offsets, a blocked cell (and the frame)
  // is -inf, and no index is divided (a third of the time of a plan along a 4-cell-wide corridor went to
  // tracePath's divisions). Every cell it reads is within two of a settled cell, so in rows the wave derived
  // in this search.
  constexpr double kBlocked = -std::numeric_limits<double>::infinity();
  const double* const dist = labels.dist;
  const int s = stride_;
  // forEachMove's order, which ties follow.
  constexpr int kDx[8] = {-1, 1, 0, 0, -1, 1, -1, 1};
  constexpr int kDy[8] = {0, 0, -1, 1, -1, -1, 1, 1};
  path->clear();
  Cell at{goal % width_, goal / width_};
  int p = padded(goal);
  path->push_back(at);
  while (std::fabs(dist[p]) > 0.0) {
    const bool fw = dist[p - 1] != kBlocked, fe = dist[p + 1] != kBlocked;
    const bool fn = dist[p - s] != kBlocked, fs = dist[p + s] != kBlocked;
    const bool legal[8] = {fw, fe, fn, fs, fn && fw, fn && fe, fs && fw, fs && fe};
    int best = -1;
    double best_dist = std::numeric_limits<double>::infinity();
    for (int k = 0; k < 8; ++k) {
      const double label = dist[p + kDy[k] * s + kDx[k]];
      // Blocked (-inf) and unsettled (positive) neighbours are no predecessors. Where the search reopens
      // cells, every finite label is the cost of a path from the source through a cell labelled at least that
      // much less, so the step to the least of them still goes down, to the source, along an optimal path.
      if (!legal[k] || label == kBlocked || (labels.trace_unsettled ? std::isinf(label) : !std::signbit(label))) {
        continue;
      }
      const double through = std::fabs(label) + (k < 4 ? 1.0 : kDiagonal);
      if (through < best_dist) {
        best_dist = through;
        best = k;
      }
    }
    // A move exists: a settled cell's predecessor on its shortest path is settled and closer.
    p += kDy[best] * s + kDx[best];
    at = {at.x + kDx[best], at.y + kDy[best]};
    path->push_back(at);
  }
  std::reverse(path->begin(), path->end());
}

DijkstraPlanner::Labels DijkstraPlanner::labels(const Wave& wave) const {
  return Labels{wave.dist, width_, stride_, wave.derived_lo, wave.derived_hi};
}

bool DijkstraPlanner::beginWaves(const std::atomic<bool>* cancel) {
  expansions_ = 0;
  cancelled_ = cancel != nullptr && cancel->load(std::memory_order_relaxed);
  return !cancelled_;
}

bool DijkstraPlanner::search(int start, int target, bool stop_at_target, const std::atomic<bool>* cancel) {
  if (!beginWaves(cancel)) return false;
  Wave wave = startWave(0, buckets_, start);
  auto nowhere = [](int, int) { return false; };
  auto no_meeting = [](int, int, double) {};
  const int goal = stop_at_target ? padded(target) : -1;
  while (wave.pending() > 0 && settleLevel(wave, goal, cancel, nowhere, no_meeting) == LevelEnd::kLevel) {
  }
  last_ = labels(wave);
  return !cancelled_ && std::signbit(last_(target));
}

// Bidirectional: a wave from each end, the one with the smaller next level goes on, each relaxation into a
// cell the other wave has labelled offers a path through that move (mu, the best so far). Every cell
// nearer than level_f to the start and every cell nearer than level_b to the target is settled. Take a
// shortest path P of length L < mu <= level_f + level_b + 1, u its last cell nearer than level_f to the
// start and v the next: v is nearer than level_b + 1 to the target, so v's successor (every move costs at
// least 1) is settled backward, and v holds exact labels from both waves; whichever of u and that
// successor was settled later offered L through v. So once level_f + level_b + 1 >= mu, mu is optimal
// (Pohl's rule with the bucket width's slack). A cell this wave has settled is skipped: P's cells lie in
// strictly different levels of each wave, so the crossing above never needs one. The moves are symmetric
// (same length and corner rule both ways), so the backward wave runs the same code.
bool DijkstraPlanner::searchBidirectional(int start, int target, const std::atomic<bool>* cancel) {
  if (!beginWaves(cancel)) return false;
  Wave forward = startWave(0, buckets_, start);
  Wave backward = startWave(1, back_buckets_, target);
  meeting_cost_ = std::numeric_limits<double>::infinity();
  meet_forward_ = meet_backward_ = -1;
  while (forward.pending() > 0 && backward.pending() > 0 &&
         static_cast<double>(forward.level + backward.level) + 1.0 < meeting_cost_) {
    // The wave with the smaller frontier goes on (the other may be in a corridor or a dead end); on a tie
    // the one with fewer levels settled, so a corridor is walked from both ends.
    const std::size_t forward_front = forward.buckets[forward.level % 3].size();
    const std::size_t backward_front = backward.buckets[backward.level % 3].size();
    const bool ahead = forward_front < backward_front ||
                       (forward_front == backward_front && forward.level <= backward.level);
    Wave& wave = ahead ? forward : backward;
    const Wave& far = ahead ? backward : forward;
    const double* const other = far.dist;
    // The other wave has labelled only cells within one of the cells it settled, so a cell whose moves can
    // reach them lies within two of that box (and the moves it offers within three: rows the other wave has
    // derived, kDerivedMargin).
    auto near = [&](int x, int y) {
      return x >= far.col_min - 2 && x <= far.col_max + 2 && y >= far.row_min - 2 && y <= far.row_max + 2;
    };
    const LevelEnd end = settleLevel(wave, -1, cancel, near, [&](int i, int j, double through) {
      const double cost = through + std::fabs(other[j]);   // +inf unless the other wave has labelled j
      if (cost < meeting_cost_) {
        meeting_cost_ = cost;
        meet_forward_ = ahead ? i : j;
        meet_backward_ = ahead ? j : i;
      }
    });
    if (end == LevelEnd::kStopped) break;
  }
  last_ = labels(forward);
  backward_ = labels(backward);
  if (meet_forward_ >= 0) {
    meet_forward_ = unpadded(meet_forward_);
    meet_backward_ = unpadded(meet_backward_);
  }
  start_component_settled_ = !cancelled_ && forward.pending() == 0;
  return !cancelled_ && meet_forward_ >= 0;
}

}  // namespace offload_planner
