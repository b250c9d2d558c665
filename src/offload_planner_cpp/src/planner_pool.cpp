#include "offload_planner_cpp/planner_pool.h"

namespace offload_planner {

PlannerPool::Lease::~Lease() {
  if (planner_) pool_->giveBack(std::move(planner_));
}

PlannerPool::Lease PlannerPool::borrow() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (!idle_.empty()) {
      std::unique_ptr<DijkstraPlanner> planner = std::move(idle_.back());
      idle_.pop_back();
      return Lease(this, std::move(planner));
    }
    ++made_;
  }
  return Lease(this, std::make_unique<DijkstraPlanner>());   // its buffers come with its first plan
}

std::size_t PlannerPool::planners() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return made_;
}

void PlannerPool::giveBack(std::unique_ptr<DijkstraPlanner> planner) {
  std::lock_guard<std::mutex> lock(mutex_);
  idle_.push_back(std::move(planner));
}

}  // namespace offload_planner
