#include "offload_planner_cpp/jump_point_search.h"
#include "diagonal_step.h"

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <new>

namespace offload_planner {
namespace {

// The open list's order: smaller f first; on equal f the larger g (the deeper cell), which on open ground
// walks on towards the goal instead of widening over every cell of equal f.
bool later(const JumpPointSearch::Open& a, const JumpPointSearch::Open& b) {
  return a.f > b.f || (a.f == b.f && a.g < b.g);
}

}  // namespace

void JumpPointSearch::FreeDeleter::operator()(std::uint32_t* p) const { std::free(p); }

void JumpPointSearch::deriveRows(int lo, int hi) {
  lo = std::max(lo, 0);
  hi = std::min(hi, height_ + 1);
  const int w = width_;
  const bool* const passable = passable_;
  auto derive = [&](int row) {
    std::uint8_t* const out = open_.get() + static_cast<std::size_t>(row) * stride_;
    if (row == 0 || row == height_ + 1) {
      std::memset(out, 0, stride_);
      return;
    }
    const std::int8_t* const cells = grid_ + static_cast<std::size_t>(row - 1) * w;
    out[0] = out[w + 1] = 0;
    for (int x = 0; x < w; ++x) out[x + 1] = passable[static_cast<std::uint8_t>(cells[x])];
  };
  if (derived_hi_ < derived_lo_) {
    for (int row = lo; row <= hi; ++row) derive(row);
    derived_lo_ = lo;
    derived_hi_ = hi;
  } else {
    for (int row = lo; row < derived_lo_; ++row) derive(row);
    for (int row = derived_hi_ + 1; row <= hi; ++row) derive(row);
    derived_lo_ = std::min(derived_lo_, lo);
    derived_hi_ = std::max(derived_hi_, hi);
  }
  // Cells whose rows within one are derived (at the frame there is nothing beyond).
  safe_begin_ = derived_lo_ == 0 ? 0 : (derived_lo_ + 1) * stride_;
  safe_end_ = derived_hi_ == height_ + 1 ? (height_ + 2) * stride_ : derived_hi_ * stride_;
}

int JumpPointSearch::scanStraight(int i, int step) {
  const std::uint8_t* const o = open_.get();
  const int target = target_;
  if (step == 1 || step == -1) {
    // Along a row: rows y - 1, y, y + 1 are derived once for the whole scan.
    reach(i);
    const int s = stride_;
    for (;;) {
      i += step;
      if (!o[i]) return -1;
      if (i == target) return i;
      // A forced neighbour: the cell beside i is free and the one beside i's predecessor blocked.
      if ((o[i - s] & !o[i - step - s]) | (o[i + s] & !o[i - step + s])) return i;
    }
  }
  for (;;) {
    i += step;
    reach(i);
    if (!o[i]) return -1;
    if (i == target) return i;
    if ((o[i - 1] & !o[i - step - 1]) | (o[i + 1] & !o[i - step + 1])) return i;
  }
}

int JumpPointSearch::scanDiagonal(int i, int dx, int dy) {
  const std::uint8_t* const o = open_.get();
  const int row_step = dy * stride_;
  for (;;) {
    // The corner rule: both orthogonal neighbours free.
    if (!(o[i + dx] & o[i + row_step])) return -1;
    i += dx + row_step;
    reach(i);
    if (!o[i]) return -1;
    if (i == target_) return i;
    if (scanStraight(i, dx) >= 0 || scanStraight(i, row_step) >= 0) return i;
  }
}

double JumpPointSearch::octile(int i) const {
  const int y = i / stride_;
  const double dx = std::abs(i - y * stride_ - target_x_);
  const double dy = std::abs(y - target_y_);
  return std::max(dx, dy) + (kDiagonal - 1.0) * std::min(dx, dy);
}

void JumpPointSearch::offer(int i, double g, int j, bool diagonal) {
  const int s = stride_;
  const int steps = diagonal || std::abs(j - i) < s ? std::abs(j % s - i % s) : std::abs(j / s - i / s);
  const double nd = g + (diagonal ? kDiagonal * steps : static_cast<double>(steps));
  Node& node = nodes_[j];
  if (stamp_[j] == search_) {
    if (!(nd < node.g)) return;  // always false once expanded (negative)
  } else {
    stamp_[j] = search_;
  }
  node.g = nd;
  node.parent = i;
  heap_.push_back({nd + octile(j), nd, j});
  std::push_heap(heap_.begin(), heap_.end(), later);
}

JumpPointSearch::Outcome JumpPointSearch::search(const std::int8_t* grid, int width, int height,
                                                 const bool (&passable)[256], int start, int target,
                                                 const std::atomic<bool>* cancel) {
  constexpr std::uint64_t kCancelCheck = 256;
  if (cancel != nullptr && cancel->load(std::memory_order_relaxed)) return Outcome::kCancelled;
  grid_ = grid;
  passable_ = passable;
  width_ = width;
  height_ = height;
  stride_ = width + 2;
  expansions_ = straight_ = diagonal_ = 0;
  path_.clear();
  const std::size_t cells = static_cast<std::size_t>(stride_) * static_cast<std::size_t>(height + 2);
  if (cells != cells_) {
    open_.reset();
    nodes_.reset();
    stamp_.reset();
    open_.reset(new std::uint8_t[cells]);
    nodes_.reset(new Node[cells]);
    stamp_.reset(static_cast<std::uint32_t*>(std::calloc(cells, sizeof(std::uint32_t))));
    if (!stamp_) throw std::bad_alloc();
    cells_ = cells;
    search_ = 0;
  }
  if (++search_ == 0) {  // the stamps wrapped: forget every earlier search
    std::memset(stamp_.get(), 0, cells * sizeof(std::uint32_t));
    search_ = 1;
  }
  derived_lo_ = 0;
  derived_hi_ = -1;
  auto pad = [&](int cell) { return (cell / width + 1) * stride_ + cell % width + 1; };
  const int from = pad(start);
  target_ = pad(target);
  target_x_ = target % width + 1;
  target_y_ = target / width + 1;
  deriveRows(from / stride_ - kAhead, from / stride_ + kAhead);
  heap_.clear();
  stamp_[from] = search_;
  nodes_[from] = {0.0, from};
  heap_.push_back({octile(from), 0.0, from});
  const int s = stride_;
  const std::uint8_t* const o = open_.get();
  while (!heap_.empty()) {
    std::pop_heap(heap_.begin(), heap_.end(), later);
    const Open top = heap_.back();
    heap_.pop_back();
    const int i = top.cell;
    Node& node = nodes_[i];
    if (std::signbit(node.g) || top.g != node.g) continue;  // expanded already, or a stale entry
    const double g = node.g;
    node.g = -g;
    ++expansions_;
    if (cancel != nullptr && expansions_ % kCancelCheck == 0 && cancel->load(std::memory_order_relaxed)) {
      return Outcome::kCancelled;
    }
    if (i == target_) {
      tracePath(from, target_);
      return Outcome::kFound;
    }
    reach(i);
    const int p = node.parent;
    // The direction of arrival from the parent (jump points lie on a straight or diagonal line from it).
    const int px = p % s, py = p / s, x = i % s, y = i / s;
    const int dx = (x > px) - (x < px);
    const int dy = (y > py) - (y < py);
    auto straight = [&](int step) {
      const int j = scanStraight(i, step);
      if (j >= 0) offer(i, g, j, false);
    };
    auto diagonal = [&](int ddx, int ddy) {
      const int j = scanDiagonal(i, ddx, ddy);
      if (j >= 0) offer(i, g, j, true);
    };
    if (p == i) {  // the start: every direction
      straight(1);
      straight(-1);
      straight(s);
      straight(-s);
      diagonal(1, 1);
      diagonal(-1, 1);
      diagonal(1, -1);
      diagonal(-1, -1);
    } else if (dx != 0 && dy != 0) {  // reached diagonally: no forced neighbours under the corner rule
      diagonal(dx, dy);
      straight(dx);
      straight(dy * s);
    } else if (dy == 0) {  // reached along a row
      straight(dx);
      for (int side : {-1, 1}) {
        if (o[i + side * s] && !o[i - dx + side * s]) {
          straight(side * s);
          diagonal(dx, side);
        }
      }
    } else {  // reached along a column
      straight(dy * s);
      for (int side : {-1, 1}) {
        if (o[i + side] && !o[i - dy * s + side]) {
          straight(side);
          diagonal(side, dy);
        }
      }
    }
  }
  return Outcome::kNoPath;
}

void JumpPointSearch::tracePath(int start, int target) {
  const int s = stride_;
  const int w = width_;
  auto cell = [&](int padded) { return (padded / s - 1) * w + padded % s - 1; };
  path_.push_back(cell(target));
  for (int i = target; i != start;) {
    const int p = nodes_[i].parent;
    const int dx = (p % s > i % s) - (p % s < i % s);
    const int dy = (p / s > i / s) - (p / s < i / s);
    const int step = dx + dy * s;
    ((dx != 0 && dy != 0) ? diagonal_ : straight_) += std::max(std::abs(p % s - i % s), std::abs(p / s - i / s));
    for (int j = i + step;; j += step) {
      path_.push_back(cell(j));
      if (j == p) break;
    }
    i = p;
  }
  std::reverse(path_.begin(), path_.end());
}

}  // namespace offload_planner
