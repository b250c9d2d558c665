// Jump point search (Harabor and Grastien) on the core's grid, with no ROS dependency: exact where every
// passable cell costs the same (cost_factor 0), under the core's moves: 8-connected, 1 and sqrt(2), a
// diagonal step only with both orthogonal neighbours free (no corner cutting, MovingAI's rule).
//
// With that corner rule a cell reached diagonally has no forced neighbour: every neighbour a diagonal
// step could prune is reached as cheaply from its parent through a free orthogonal cell. A cell reached
// straight, say east from (x - 1, y), has a forced neighbour (x, y + 1) exactly when (x - 1, y + 1) is
// blocked and (x, y + 1) free (else its parent reaches it diagonally for sqrt(2) < 2); it then goes on
// north and north-east as well. A diagonal scan stops at a cell whose straight scans along its two
// components find a jump point. Every optimal path has a diagonal-first twin of the same length whose
// turns are jump points, so A* over jump points (octile heuristic, consistent) returns an optimal length.
#pragma once

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <vector>

namespace offload_planner {

class JumpPointSearch {
 public:
  enum class Outcome { kFound, kNoPath, kCancelled };
  // Searches from cell `start` to cell `target` (indices y * width + x of a width x height grid; both
  // passable, different). `passable` maps an occupancy, as uint8 (-1 unknown is 255), to whether a cell may
  // be entered. On kFound, path() holds every cell from start to target, and straight() and diagonal() its
  // step counts.
  Outcome search(const std::int8_t* grid, int width, int height, const bool (&passable)[256], int start,
                 int target, const std::atomic<bool>* cancel);
  const std::vector<int>& path() const { return path_; }   // cell indices, start to target
  std::uint64_t straight() const { return straight_; }
  std::uint64_t diagonal() const { return diagonal_; }
  std::uint64_t expansions() const { return expansions_; }  // jump points taken off the open list

 // The open list's entries (public for its order's comparison).
  struct Open {
    double f;
    double g;
    int cell;
  };

 private:
  // Per padded cell, touched only at jump points: stamp_ says whether g and parent belong to this search.
  struct Node {
    double g;       // negated once expanded (the start: -0.0)
    int parent;     // padded index; the start is its own parent
  };
  // Derives padded rows [lo, hi] (clipped to the frame) of open_ from the grid, where not yet.
  void deriveRows(int lo, int hi);
  // Readies the rows within one of padded cell i.
  void reach(int i) {
    if (i < safe_begin_ || i >= safe_end_) deriveRows(i / stride_ - kAhead, i / stride_ + kAhead);
  }
  // The next jump point from i moving by `step` (±1 along a row, ±stride_ along a column), or -1.
  int scanStraight(int i, int step);
  // The next jump point from i moving by (dx, dy), or -1.
  int scanDiagonal(int i, int dx, int dy);
  // Offers jump point j, `steps` moves from the expanded cell i (at cost g), to the open list.
  void offer(int i, double g, int j, bool diagonal);
  double octile(int i) const;
  void tracePath(int start, int target);

  static constexpr int kAhead = 16;
  const std::int8_t* grid_ = nullptr;
  const bool* passable_ = nullptr;
  int width_ = 0;
  int height_ = 0;
  int stride_ = 0;
  int target_ = -1;
  int target_x_ = 0;
  int target_y_ = 0;
  // Reused between calls, allocated but never filled whole: open_ (1 free, 0 blocked, with a frame of one
  // blocked cell) gets its rows from the grid as the search reaches them; nodes_ count only where stamp_ holds
  // this search's number (calloc'd, so untouched pages cost no memory).
  std::unique_ptr<std::uint8_t[]> open_;
  std::unique_ptr<Node[]> nodes_;
  struct FreeDeleter {
    void operator()(std::uint32_t* p) const;
  };
  std::unique_ptr<std::uint32_t[], FreeDeleter> stamp_;
  std::size_t cells_ = 0;
  std::uint32_t search_ = 0;
  int derived_lo_ = 0;
  int derived_hi_ = -1;
  int safe_begin_ = 0;
  int safe_end_ = 0;
  std::vector<Open> heap_;
  std::vector<int> path_;
  std::uint64_t straight_ = 0;
  std::uint64_t diagonal_ = 0;
  std::uint64_t expansions_ = 0;
};

}  // namespace offload_planner
