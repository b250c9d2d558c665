// The planner node's serving: threads sharing a queue run callbacks that arrive together side by side, and a cancel
// reaches the plan it names (CancelRegistry).
#include <gtest/gtest.h>

#include <chrono>
#include <cstdint>
#include <condition_variable>
#include <mutex>
#include <thread>
#include <vector>

#include <boost/make_shared.hpp>
#include <ros/callback_queue.h>

#include "offload_planner_cpp/planner_ros.h"

namespace {

// A callback that waits (up to 5 s) for `expected` callbacks to be running at once, as a long plan runs while
// another is asked; it records how many it saw.
struct Rendezvous {
  std::mutex mutex;
  std::condition_variable changed;
  int running = 0;
  std::vector<int> seen;
};

class WaitForOthers : public ros::CallbackInterface {
 public:
  WaitForOthers(Rendezvous* meet, int expected) : meet_(meet), expected_(expected) {}
  CallResult call() override {
    std::unique_lock<std::mutex> lock(meet_->mutex);
    ++meet_->running;
    meet_->changed.notify_all();
    meet_->changed.wait_for(lock, std::chrono::seconds(5), [&] { return meet_->running >= expected_; });
    meet_->seen.push_back(meet_->running);
    meet_->changed.notify_all();
    return Success;
  }

 private:
  Rendezvous* meet_;
  int expected_;
};

}  // namespace

TEST(ServeQueue, CallbacksQueuedTogetherRunOnSeparateThreads) {
  ros::CallbackQueue queue;
  Rendezvous meet;
  // Both are waiting before any thread looks: the first thread to wake must not take them both.
  for (int k = 0; k < 2; ++k) queue.addCallback(boost::make_shared<WaitForOthers>(&meet, 2));
  std::vector<std::thread> threads;
  for (int k = 0; k < 2; ++k) threads.emplace_back(offload_planner::serveQueue, &queue, 0.05);
  {
    std::unique_lock<std::mutex> lock(meet.mutex);
    meet.changed.wait_for(lock, std::chrono::seconds(15), [&] { return meet.seen.size() == 2; });
  }
  queue.disable();
  for (auto& thread : threads) thread.join();
  EXPECT_EQ(meet.seen, (std::vector<int>{2, 2})) << "a callback ran only after the other had ended";
}

TEST(ServeQueue, ReturnsOnceTheQueueIsDisabled) {
  ros::CallbackQueue queue;
  std::thread server(offload_planner::serveQueue, &queue, 30.0);
  std::this_thread::sleep_for(std::chrono::milliseconds(50));
  const auto disabled = std::chrono::steady_clock::now();
  queue.disable();   // wakes a thread waiting for work
  server.join();
  EXPECT_LT(std::chrono::steady_clock::now() - disabled, std::chrono::seconds(10));
}

using offload_planner::CancelRegistry;

TEST(CancelRegistry, ACancelReachesTheRunningPlanOrWaitsForItsStart) {
  CancelRegistry registry;
  auto running = registry.begin(7);
  EXPECT_FALSE(running->load());
  registry.cancel(7);
  EXPECT_TRUE(running->load()) << "a running plan sees its cancel";
  registry.end(7);
  EXPECT_EQ(registry.running(), 0u);
  registry.cancel(8);   // the cancel overtook its request
  EXPECT_TRUE(registry.begin(8)->load()) << "a plan cancelled before it began never runs";
  registry.end(8);
  EXPECT_FALSE(registry.begin(8)->load()) << "the early cancel is used once";
  registry.end(8);
  EXPECT_FALSE(registry.begin(9)->load()) << "other plans are untouched";
  registry.end(9);
}

TEST(CancelRegistry, RemembersOnlyTheLatestEarlyCancels) {
  CancelRegistry registry;
  for (std::uint64_t id = 1; id <= CancelRegistry::kRemembered + 10; ++id) registry.cancel(id);
  EXPECT_FALSE(registry.begin(1)->load()) << "the oldest early cancels are forgotten: memory stays bounded";
  EXPECT_TRUE(registry.begin(CancelRegistry::kRemembered + 10)->load());
  EXPECT_TRUE(registry.begin(11)->load());
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
