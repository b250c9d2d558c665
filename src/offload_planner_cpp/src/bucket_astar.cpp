// A* at uniform cost on a bucket queue (searchBucketAStar): the waves' padded buffer, buckets of width one half on
// f = g + octile distance to the target, cells reopened when improved. See dijkstra.h.
#include "offload_planner_cpp/dijkstra.h"
#include "diagonal_step.h"

#include <algorithm>
#include <cmath>
#include <limits>

namespace offload_planner {

// Dial's rule (a bucket settles exactly) needs every move to raise f by at least the bucket width; measured
// against the octile heuristic a move may leave f unchanged, so a cell taken from a bucket may still improve
// through another cell of the same bucket. Such a cell is simply queued again (a label-correcting search):
// whatever the order within a bucket, every cell whose f is below the best cost to the target found so far is
// expanded with its final distance before the search stops, and the octile heuristic is consistent, so the
// target's cost is the optimum. A move that raises f raises it by at least 2 - sqrt 2 = 0.59, so with buckets of
// width one half only the moves that keep f can reopen a cell (width one: 1.24 M expansions corner to corner on
// the 2000 x 2000 20 % grid, one half 1.19 M, a quarter 1.18 M in the same time; a heap settles 1.17 M). f rises
// by at most 2 sqrt 2 < 3 per move, six buckets ahead: a ring of eight holds everything pending.
bool DijkstraPlanner::searchBucketAStar(int start, int target, const std::atomic<bool>* cancel) {
  constexpr std::uint64_t kCancelCheck = 4096;
  constexpr double kBlocked = -std::numeric_limits<double>::infinity();
  constexpr int kRing = 8;
  constexpr double kPerUnit = 2.0;  // buckets per unit of f: width one half
  constexpr int kDeriveAheadRows = 16;  // rows derived at a time, as the waves do
  if (!beginWaves(cancel)) return false;
  Bucket* const buckets = astar_buckets_;
  Wave wave = startWave(0, buckets, start);  // the source in buckets[0], its rows derived
  for (int k = 3; k < kRing; ++k) buckets[k].clear();
  double* const dist = wave.dist;
  const int s = stride_;
  const int goal = padded(target);
  const int offset[8] = {-1, 1, -s, s, -s - 1, -s + 1, s - 1, s + 1};
  constexpr int kDx[8] = {-1, 1, 0, 0, -1, 1, -1, 1};
  constexpr int kDy[8] = {0, 0, -1, 1, -1, -1, 1, 1};
  const int gx = goal % s;
  const int gy = goal / s;
  auto estimate = [&](int x, int y) {
    const int dx = std::abs(x - gx);
    const int dy = std::abs(y - gy);
    return static_cast<double>(std::max(dx, dy)) + (kDiagonal - 1.0) * static_cast<double>(std::min(dx, dy));
  };
  const int source = padded(start);
  std::size_t level = static_cast<std::size_t>(kPerUnit * estimate(source % s, source / s));
  if (level % kRing != 0) {  // the source belongs in its own level's bucket
    std::swap(buckets[0], buckets[level % kRing]);
  }
  double bound = std::numeric_limits<double>::infinity();  // the best cost to the target so far
  std::uint64_t expansions = 0;
  int safe_begin = wave.safe_begin;
  int safe_end = wave.safe_end;
  std::size_t empty_levels = 0;
  while (empty_levels < kRing && static_cast<double>(level) < kPerUnit * bound) {
    Bucket& bucket = buckets[level % kRing];
    if (bucket.size() == 0) {
      ++empty_levels;
      ++level;
      continue;
    }
    empty_levels = 0;
    // In rounds: moves whose f does not leave this level append to this bucket while it is read.
    for (std::size_t begin = 0; begin < bucket.size();) {
      const std::size_t round_end = bucket.size();
      int* ends[kRing];
      for (int k = 0; k < kRing; ++k) {
        buckets[k].reserveMore(8 * (round_end - begin));
        ends[k] = buckets[k].end();
      }
      const int* const entry = bucket.data();
      for (std::size_t k = begin; k < round_end; ++k) {
        const int i = entry[k];
        if (k + 8 < round_end) {
          const int ahead = entry[k + 8];
          __builtin_prefetch(dist + ahead - s, 1);
          __builtin_prefetch(dist + ahead, 1);
          __builtin_prefetch(dist + ahead + s, 1);
        }
        const double d = dist[i];
        if (std::signbit(d)) continue;  // expanded with this distance already (a stale duplicate)
        const int y = i / s;
        const int x = i - y * s;
        // Cannot lead to a cheaper path to the target. Tested only once the target has a cost: the estimate for
        // every cell before that, in vain, took 13 % of the search (55 -> 48 ms corner to corner on 2000 x 2000).
        if (bound != std::numeric_limits<double>::infinity() && !(d + estimate(x, y) < bound)) continue;
        dist[i] = -d;
        ++expansions;
        if (cancel != nullptr && expansions % kCancelCheck == 0 && cancel->load(std::memory_order_relaxed)) {
          cancelled_ = true;
          break;
        }
        if (i < safe_begin || i >= safe_end) {
          deriveRows(wave, y - kDeriveAheadRows, y + kDeriveAheadRows);
          safe_begin = wave.safe_begin;
          safe_end = wave.safe_end;
        }
        const bool fw = dist[i - 1] != kBlocked;
        const bool fe = dist[i + 1] != kBlocked;
        const bool fn = dist[i - s] != kBlocked;
        const bool fs = dist[i + s] != kBlocked;
        const double d1 = d + 1.0;
        const double d2 = d + kDiagonal;
        // Which moves improve their cell, without a branch per move (whether one does is a coin toss on
        // clutter), then a pass over the improving ones: one mispredicted loop exit per cell instead of up to
        // eight (46 -> 41 ms on the grid above). Only those compute an f (the waves' push of every move, with
        // its f, was slower here).
        auto better = [&](int j, double nd, bool legal) {
          const double old = dist[j];
          return static_cast<unsigned>(legal & (old != kBlocked) & (nd < std::fabs(old)));
        };
        unsigned mask = better(i - 1, d1, true) | better(i + 1, d1, true) << 1 | better(i - s, d1, true) << 2 |
                        better(i + s, d1, true) << 3 | better(i - s - 1, d2, fn & fw) << 4 |
                        better(i - s + 1, d2, fn & fe) << 5 | better(i + s - 1, d2, fs & fw) << 6 |
                        better(i + s + 1, d2, fs & fe) << 7;
        while (mask != 0) {
          const int k = __builtin_ctz(mask);
          mask &= mask - 1;
          const int j = i + offset[k];
          const double nd = k < 4 ? d1 : d2;
          dist[j] = nd;
          const double f = nd + estimate(x + kDx[k], y + kDy[k]);
          const std::size_t at = std::max(level, static_cast<std::size_t>(kPerUnit * f)) % kRing;
          *ends[at]++ = j;
          if (j == goal) bound = nd;
        }
      }
      for (int k = 0; k < kRing; ++k) buckets[k].setEnd(ends[k]);
      if (cancelled_) break;
      begin = round_end;
    }
    if (cancelled_) break;
    bucket.clear();
    ++level;
  }
  expansions_ = expansions;
  last_ = labels(wave);
  last_.trace_unsettled = true;
  return !cancelled_ && bound < std::numeric_limits<double>::infinity();
}

}  // namespace offload_planner
