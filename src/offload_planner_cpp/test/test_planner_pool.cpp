// PlannerPool: plans one at a time reuse one planner (its buffers paged in and warm), whatever thread runs them;
// plans at once never share one.
#include <gtest/gtest.h>

#include <atomic>
#include <cmath>
#include <map>
#include <mutex>
#include <thread>
#include <vector>

#include "offload_planner_cpp/planner_pool.h"

using namespace offload_planner;

TEST(PlannerPool, PlansOneAtATimeReuseOnePlannerFromAnyThread) {
  PlannerPool pool;
  const DijkstraPlanner* first = &*pool.borrow();
  for (int k = 0; k < 4; ++k) {   // as a node's serving threads take turns at a robot's sequential requests
    std::thread([&] { EXPECT_EQ(&*pool.borrow(), first); }).join();
  }
  EXPECT_EQ(pool.planners(), 1u);
}

TEST(PlannerPool, OverlappingPlansGetTheirOwnAndTheOneReturnedLastComesFirst) {
  PlannerPool pool;
  const DijkstraPlanner* a;
  const DijkstraPlanner* b;
  {
    PlannerPool::Lease first = pool.borrow();
    PlannerPool::Lease second = pool.borrow();
    a = &*first;
    b = &*second;
    EXPECT_NE(a, b);
  }   // `second` ends first, then `first`: `first`'s planner was returned last
  EXPECT_EQ(pool.planners(), 2u);
  EXPECT_EQ(&*pool.borrow(), a);
}

TEST(PlannerPool, ConcurrentPlansNeverShareAPlannerAndAllFindTheirPath) {
  // An empty 64 x 64 grid: from (0, y) to (63, y) costs 63 cells on every plan, unless two plans share buffers.
  const int side = 64;
  const std::vector<std::int8_t> grid(side * side, 0);
  PlannerPool pool;
  std::mutex mutex;
  std::map<const DijkstraPlanner*, int> in_use;
  std::atomic<int> shared{0}, wrong{0};
  std::vector<std::thread> threads;
  for (int t = 0; t < 6; ++t) {
    threads.emplace_back([&, t] {
      for (int k = 0; k < 150; ++k) {
        PlannerPool::Lease planner = pool.borrow();
        {
          std::lock_guard<std::mutex> lock(mutex);
          if (in_use[&*planner]++ != 0) ++shared;
        }
        const int y = (t * 7 + k) % side;
        const PlanResult result = planner->plan(grid.data(), grid.size(), side, side, {0, y}, {side - 1, y});
        if (!result.ok() || std::fabs(result.cost - (side - 1)) > 1e-9) ++wrong;
        std::lock_guard<std::mutex> lock(mutex);
        --in_use[&*planner];
      }
    });
  }
  for (auto& thread : threads) thread.join();
  EXPECT_EQ(shared.load(), 0);
  EXPECT_EQ(wrong.load(), 0);
  EXPECT_LE(pool.planners(), 6u);
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
