// Planners lent out most recently returned first, for callers that plan from several threads.
#pragma once

#include "offload_planner_cpp/dijkstra.h"

#include <cstddef>
#include <memory>
#include <mutex>
#include <vector>

namespace offload_planner {

// A planner's search buffers hold 8 bytes per cell for each of its two waves (67 MB on a 2048 x 2048 map), paged
// in as its searches first reach each row: on that map about a thousand page faults, 5 ms, in each of its first ten
// plans. With a planner per thread, every serving thread paid that warm-up and kept its own buffers, though a robot
// asks for one plan at a time (#30: the deployed DQN's sporadic local plans cost 5 ms more each than always-local's).
// Lent most recently returned first, one planner serves every plan that overlaps no other, whichever thread runs
// it; another is made only when plans run at once.
class PlannerPool {
 public:
  // A planner on loan; it returns to the pool when the lease ends.
  class Lease {
   public:
    Lease(Lease&&) = default;
    Lease& operator=(Lease&&) = delete;
    Lease(const Lease&) = delete;
    Lease& operator=(const Lease&) = delete;
    ~Lease();
    DijkstraPlanner& operator*() const { return *planner_; }
    DijkstraPlanner* operator->() const { return planner_.get(); }

   private:
    friend class PlannerPool;
    Lease(PlannerPool* pool, std::unique_ptr<DijkstraPlanner> planner) : pool_(pool), planner_(std::move(planner)) {}
    PlannerPool* pool_;
    std::unique_ptr<DijkstraPlanner> planner_;
  };

  // Thread safe: the planner returned last, or a new one when every planner is on loan.
  Lease borrow();
  // Planners made so far: the most plans that ran at once.
  std::size_t planners() const;

 private:
  void giveBack(std::unique_ptr<DijkstraPlanner> planner);

  mutable std::mutex mutex_;
  std::vector<std::unique_ptr<DijkstraPlanner>> idle_;  // the one returned last at the back
  std::size_t made_ = 0;
};

}  // namespace offload_planner
