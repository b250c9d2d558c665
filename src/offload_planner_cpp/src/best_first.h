// The moves of a cell and the heap best-first search over them, used by the heap searches (dijkstra.cpp:
// weighted Dijkstra and A*). Internal to the core: not installed; member templates
// defined here so each file that runs a search instantiates its own.
#ifndef OFFLOAD_PLANNER_CPP_BEST_FIRST_H
#define OFFLOAD_PLANNER_CPP_BEST_FIRST_H

#include "offload_planner_cpp/dijkstra.h"
#include "diagonal_step.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <utility>

namespace offload_planner {

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

}  // namespace offload_planner

#endif  // OFFLOAD_PLANNER_CPP_BEST_FIRST_H
