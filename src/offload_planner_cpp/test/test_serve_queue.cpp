// The planner node's serving loop: threads sharing a queue run callbacks that arrive together side by side.
#include <gtest/gtest.h>

#include <chrono>
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

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
