// offload_bag_recorder: the robot's recorder of the offloading topics, one callback thread.
//
// Why not `rosbag record` itself: its recorder spins ten callback threads that each wake ten times a second
// with nothing to do. On this machine that cost 5-7 ms of the robot's CPU every second with no request in
// flight, 1.4 ms a request at the bench's 4 requests a second: as much as the learner's own work. The
// offloading topics carry a few messages a request, so one thread writes each as it arrives, through the
// same library rosbag record writes with (rosbag_storage), into the same file: BAG.active while recording,
// renamed to BAG when it closes, each message with its publisher's connection header (latching kept) and
// stamped on arrival. A crashed recorder leaves BAG.active, which the learner's bag reader reads as before.
//
//   offload_bag_recorder [--min-free-mib N] BAG TOPIC...
// offload_record checks that BAG is new and that the disk has room, then becomes this (exec). Below
// --min-free-mib during the run it stops writing, says so, and keeps what it wrote (as rosbag record does).
#include <sys/statvfs.h>

#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

#include <boost/bind/bind.hpp>
#include <boost/make_shared.hpp>
#include <ros/callback_queue.h>
#include <ros/ros.h>
#include <rosbag/bag.h>
#include <rosbag/exceptions.h>
#include <topic_tools/shape_shifter.h>

namespace {

using Event = ros::MessageEvent<topic_tools::ShapeShifter const>;
constexpr uint32_t kChunkBytes = 768 * 1024;   // rosbag record's default chunk size
constexpr double kSpaceCheckS = 20.0;          // as often as rosbag record checks the disk

uint64_t free_mib(const std::string& path) {
  struct statvfs fs {};
  if (statvfs(path.c_str(), &fs) != 0) return UINT64_MAX;   // cannot tell: keep recording
  return static_cast<uint64_t>(fs.f_bavail) * fs.f_frsize >> 20;
}

class BagRecorder {
 public:
  BagRecorder(const std::string& path, const std::vector<std::string>& topics, uint64_t min_free_mib)
      : path_(path), active_(path + ".active"), min_free_mib_(min_free_mib) {
    bag_.open(active_, rosbag::bagmode::Write);
    bag_.setChunkThreshold(kChunkBytes);
    for (const std::string& topic : topics) {
      ros::SubscribeOptions options;
      options.topic = topic;
      options.queue_size = 100;
      options.md5sum = ros::message_traits::md5sum<topic_tools::ShapeShifter>();
      options.datatype = ros::message_traits::datatype<topic_tools::ShapeShifter>();
      options.helper = boost::make_shared<ros::SubscriptionCallbackHelperT<const Event&>>(
          boost::bind(&BagRecorder::write, this, boost::placeholders::_1, topic));
      subscribers_.push_back(node_.subscribe(options));
    }
    space_timer_ = node_.createWallTimer(ros::WallDuration(kSpaceCheckS), [this](const ros::WallTimerEvent&) {
      check_space();
    });
    check_space();
  }

  // Closes the bag (its index written) and gives it its final name; false when either failed.
  bool close() {
    subscribers_.clear();
    try {
      bag_.close();
    } catch (const rosbag::BagException& error) {
      ROS_ERROR("closing %s: %s (its records stay in %s)", path_.c_str(), error.what(), active_.c_str());
      return false;
    }
    if (std::rename(active_.c_str(), path_.c_str()) != 0) {
      ROS_ERROR("cannot rename %s to %s", active_.c_str(), path_.c_str());
      return false;
    }
    ROS_INFO("recorded %lu messages into %s", static_cast<unsigned long>(written_), path_.c_str());
    return !failed_;
  }

 private:
  void write(const Event& event, const std::string& topic) {
    if (stopped_ || failed_) return;
    try {
      bag_.write(topic, ros::Time::now(), event.getConstMessage(), event.getConnectionHeaderPtr());
      ++written_;
    } catch (const rosbag::BagException& error) {
      // A bag that cannot be written to records nothing more; the robot's nodes keep running.
      ROS_ERROR("writing %s to %s failed, recording stopped: %s", topic.c_str(), active_.c_str(), error.what());
      failed_ = true;
    }
  }

  void check_space() {
    const std::string directory = path_.find('/') == std::string::npos ? "." : path_.substr(0, path_.rfind('/') + 1);
    const uint64_t free = free_mib(directory);
    if (!stopped_ && free < min_free_mib_) {
      ROS_ERROR("only %lu MiB free for %s, under %lu: recording stopped (free space and restart the recorder)",
                static_cast<unsigned long>(free), path_.c_str(), static_cast<unsigned long>(min_free_mib_));
      stopped_ = true;
    }
  }

  ros::NodeHandle node_;
  rosbag::Bag bag_;
  std::string path_, active_;
  uint64_t min_free_mib_;
  std::vector<ros::Subscriber> subscribers_;
  ros::WallTimer space_timer_;
  uint64_t written_ = 0;
  bool stopped_ = false, failed_ = false;
};

// roslaunch stops a node with SIGINT, then SIGTERM: both close the bag (roscpp's own handler takes SIGINT).
void on_terminate(int) { ros::requestShutdown(); }

}  // namespace

int main(int argc, char** argv) {
  ros::init(argc, argv, "offload_bag_recorder");   // strips __name:= and the other remappings
  uint64_t min_free_mib = 1024;
  std::vector<std::string> words(argv + 1, argv + argc);
  if (words.size() >= 2 && words[0] == "--min-free-mib") {
    char* end = nullptr;
    min_free_mib = std::strtoull(words[1].c_str(), &end, 10);
    if (words[1].empty() || *end != '\0' || words[1][0] == '-') {   // strtoull takes "-1" and stops at garbage
      std::fprintf(stderr, "offload_bag_recorder: --min-free-mib wants a whole number of MiB, got '%s'\n",
                   words[1].c_str());
      return 2;
    }
    words.erase(words.begin(), words.begin() + 2);
  }
  if (words.size() < 2) {
    std::fprintf(stderr, "usage: offload_bag_recorder [--min-free-mib N] BAG TOPIC...\n");
    return 2;
  }
  const std::vector<std::string> topics(words.begin() + 1, words.end());
  std::signal(SIGTERM, on_terminate);
  try {
    BagRecorder recorder(words[0], topics, min_free_mib);
    // One thread runs the callbacks and the disk check. ros::spin() wakes it ten times a second to look for a
    // shutdown that ros::shutdown() announces anyway (it disables the queue, which wakes this wait): once a
    // second is enough. Each wake-up costs the robot 50-60 us of CPU on this machine.
    ros::CallbackQueue* queue = ros::getGlobalCallbackQueue();
    while (ros::ok()) queue->callAvailable(ros::WallDuration(1.0));
    return recorder.close() ? 0 : 1;
  } catch (const rosbag::BagException& error) {
    std::fprintf(stderr, "offload_bag_recorder: cannot record into %s: %s\n", words[0].c_str(), error.what());
    return 1;
  }
}
