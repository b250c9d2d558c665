// A* at uniform cost on a bucket queue (searchBucketAStar): the waves' padded buffer, buckets of width one on
// f = g + octile distance to the target, cells reopened when improved. See dijkstra.h.
#include "offload_planner_cpp/dijkstra.h"
#include "diagonal_step.h"

#include <algorithm>
#include <cmath>
#include <limits>

namespace offload_planner {

// Dial's rule (a bucket of width one settles exactly) needs every move to cost at least the width; measured
// against the octile heuristic a move may cost nothing (its f does not rise), so a cell taken from a bucket
// may still improve through another cell of the same bucket. Such a cell is simply queued again (a label-
// correcting search): whatever the order within a bucket, every cell whose f is below the best cost to the
// target found so far is expanded with its final distance before the search stops, and the octile heuristic
// is consistent, so the target's cost is the optimum. f rises by at most 2 sqrt 2 < 3 per move, so four
// buckets in a ring hold everything pending.
bool DijkstraPlanner::searchBucketAStar(int start, int target, const std::atomic<bool>* cancel) {
  constexpr std::uint64_t kCancelCheck = 4096;
  constexpr double kBlocked = -std::numeric_limits<double>::infinity();
  constexpr int kRing = 4;
  constexpr int kDeriveAheadRows = 16;  // rows derived at a time, as the waves do
  if (!beginWaves(cancel)) return false;
  Bucket* const buckets = astar_buckets_;
  Wave wave = startWave(0, buckets, start);  // the source in buckets[0], its rows derived
  buckets[3].clear();
  double* const dist = wave.dist;
  const int s = stride_;
  const int goal = padded(target);
  const int gx = goal % s;
  const int gy = goal / s;
  auto estimate = [&](int x, int y) {
    const int dx = std::abs(x - gx);
    const int dy = std::abs(y - gy);
    return static_cast<double>(std::max(dx, dy)) + (kDiagonal - 1.0) * static_cast<double>(std::min(dx, dy));
  };
  const int source = padded(start);
  std::size_t level = static_cast<std::size_t>(estimate(source % s, source / s));
  if (level % kRing != 0) {  // the source belongs in its own level's bucket
    std::swap(buckets[0], buckets[level % kRing]);
  }
  double bound = std::numeric_limits<double>::infinity();  // the best cost to the target so far
  std::uint64_t expansions = 0;
  int safe_begin = wave.safe_begin;
  int safe_end = wave.safe_end;
  std::size_t empty_levels = 0;
  while (empty_levels < kRing && static_cast<double>(level) < bound) {
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
        if (!(d + estimate(x, y) < bound)) continue;  // cannot lead to a cheaper path to the target
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
        auto relax = [&](int j, int jx, int jy, double nd, bool legal) {
          const double old = dist[j];
          // Blocked cells hold -inf; an expanded cell (negative) reopens when the move improves it.
          const bool better = legal & (old != kBlocked) & (nd < std::fabs(old));
          if (!better) return;
          dist[j] = nd;
          const double f = nd + estimate(jx, jy);
          const std::size_t at = std::max(level, static_cast<std::size_t>(f)) % kRing;
          *ends[at]++ = j;
          if (j == goal) bound = nd;
        };
        const double d1 = d + 1.0;
        const double d2 = d + kDiagonal;
        relax(i - 1, x - 1, y, d1, true);
        relax(i + 1, x + 1, y, d1, true);
        relax(i - s, x, y - 1, d1, true);
        relax(i + s, x, y + 1, d1, true);
        relax(i - s - 1, x - 1, y - 1, d2, fn & fw);
        relax(i - s + 1, x + 1, y - 1, d2, fn & fe);
        relax(i + s - 1, x - 1, y + 1, d2, fs & fw);
        relax(i + s + 1, x + 1, y + 1, d2, fs & fe);
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
