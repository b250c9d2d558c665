// The ROS request handler without a master: world/cell conversion, frames, malformed maps, statuses.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <thread>
#include <utility>

#include "offload_planner_cpp/planner_ros.h"

using namespace offload_planner;
using offload_msgs::PlanPath;

namespace {

// 10 x 6 cells at 0.5 m, origin (-2, 1); a wall at x = 4 for y = 0..4 (gap at the top row y = 5).
nav_msgs::OccupancyGrid::Ptr makeMap() {
  nav_msgs::OccupancyGrid::Ptr map(new nav_msgs::OccupancyGrid);
  map->header.frame_id = "map";
  map->header.stamp = ros::Time(42, 0);
  map->info.resolution = 0.5f;
  map->info.width = 10;
  map->info.height = 6;
  map->info.origin.position.x = -2.0;
  map->info.origin.position.y = 1.0;
  map->info.origin.orientation.w = 1.0;
  map->data.assign(60, 0);
  for (int y = 0; y < 5; ++y) map->data[y * 10 + 4] = 100;
  return map;
}

PlanPath::Request request(double sx, double sy, double gx, double gy, const std::string& frame = "map") {
  PlanPath::Request req;
  req.start.header.frame_id = frame;
  req.goal.header.frame_id = frame;
  req.start.pose.position.x = sx;
  req.start.pose.position.y = sy;
  req.goal.pose.position.x = gx;
  req.goal.pose.position.y = gy;
  req.goal.pose.orientation.w = 1.0;
  return req;
}

// World coordinates of cell (x, y)'s centre on makeMap().
double wx(int x) { return -2.0 + (x + 0.5) * 0.5; }
double wy(int y) { return 1.0 + (y + 0.5) * 0.5; }

}  // namespace

TEST(MapGeometry, RoundTripsWithOffsetAndRotation) {
  MapGeometry g;
  g.resolution = 0.05;
  g.origin_x = -12.3;
  g.origin_y = 4.5;
  g.width = 400;
  g.height = 300;
  for (double yaw : {0.0, 0.3, -2.0}) {
    g.origin_yaw = yaw;
    for (Cell c : {Cell{0, 0}, Cell{399, 0}, Cell{0, 299}, Cell{123, 77}}) {
      double x, y;
      g.cellToWorld(c, &x, &y);
      Cell back;
      ASSERT_TRUE(g.worldToCell(x, y, &back));
      EXPECT_EQ(back, c) << "yaw " << yaw;
    }
  }
  g.origin_yaw = 0;
  Cell c;
  EXPECT_TRUE(g.worldToCell(-12.3, 4.5, &c));
  EXPECT_EQ(c, (Cell{0, 0}));
  EXPECT_FALSE(g.worldToCell(-12.31, 4.6, &c));  // left of the origin
  EXPECT_FALSE(g.worldToCell(-12.2, 4.49, &c));  // below it
  EXPECT_FALSE(g.worldToCell(-12.3 + 20.0, 4.6, &c));  // x = width exactly
  EXPECT_FALSE(g.worldToCell(-12.2, 4.5 + 15.0, &c));  // y = height exactly
  EXPECT_FALSE(g.worldToCell(NAN, 5.0, &c));
}

TEST(MapGeometry, ReadsEveryFieldOfMapMetaData) {
  auto map = makeMap();
  map->info.origin.orientation.z = std::sin(0.35);  // yaw 0.7 about z
  map->info.origin.orientation.w = std::cos(0.35);
  map->info.origin.position.x = 1.5;
  map->info.origin.position.y = -2.5;
  map->info.resolution = 0.1f;
  MapGeometry g;
  ASSERT_TRUE(checkMap(mapInfoOf(*map), 0, &g).ok());
  EXPECT_NEAR(g.origin_yaw, 0.7, 1e-9);
  EXPECT_DOUBLE_EQ(g.origin_x, 1.5);
  EXPECT_DOUBLE_EQ(g.origin_y, -2.5);
  EXPECT_NEAR(g.resolution, 0.1, 1e-7);
  EXPECT_EQ(g.width, 10);
  EXPECT_EQ(g.height, 6);
}

TEST(MapGeometry, YawOfAQuaternionOfAnyLengthAsTf2GetYaw) {
  auto map = makeMap();
  MapGeometry g;
  // (0, 0, 10, 10) is a 90 degree turn about z, only not of unit length.
  map->info.origin.orientation.z = 10.0;
  map->info.origin.orientation.w = 10.0;
  ASSERT_TRUE(checkMap(mapInfoOf(*map), 0, &g).ok());
  EXPECT_NEAR(g.origin_yaw, M_PI / 2, 1e-12);
  // A yaw of -2 rad, scaled by 0.01.
  map->info.origin.orientation.z = 0.01 * std::sin(-1.0);
  map->info.origin.orientation.w = 0.01 * std::cos(-1.0);
  ASSERT_TRUE(checkMap(mapInfoOf(*map), 0, &g).ok());
  EXPECT_NEAR(g.origin_yaw, -2.0, 1e-12);
  // No heading at all is an error, not yaw 0.
  map->info.origin.orientation.z = 0.0;
  map->info.origin.orientation.w = 0.0;
  const Outcome zero = checkMap(mapInfoOf(*map), 0, &g);
  EXPECT_EQ(zero.status, PlanStatus::kInvalidMap);
  EXPECT_NE(zero.message.find("zero quaternion"), std::string::npos) << zero.message;
}

TEST(PlanRequestHandler, GoalsOnAMapTurnedByANonUnitQuaternion) {
  // The map turned 90 degrees about its origin by (0, 0, 10, 10): cell (x, y) has its centre at
  // origin + (-(y + 0.5), x + 0.5) * resolution.
  auto map = makeMap();
  map->info.origin.orientation.z = 10.0;
  map->info.origin.orientation.w = 10.0;
  PlanRequestHandler handler;
  ASSERT_TRUE(handler.setMap(map, nullptr));
  const auto centre = [](int x, int y) { return std::make_pair(-2.0 - (y + 0.5) * 0.5, 1.0 + (x + 0.5) * 0.5); };
  const auto s = centre(1, 0);
  const auto g = centre(8, 0);
  PlanPath::Response res;
  handler.handle(request(s.first, s.second, g.first, g.second), &res);
  ASSERT_EQ(res.status, PlanPath::Response::OK) << res.message;
  // The same path as on the unturned map.
  PlanRequestHandler straight;
  ASSERT_TRUE(straight.setMap(makeMap(), nullptr));
  PlanPath::Response expected;
  straight.handle(request(wx(1), wy(0), wx(8), wy(0)), &expected);
  ASSERT_EQ(expected.status, PlanPath::Response::OK);
  EXPECT_DOUBLE_EQ(res.cost_m, expected.cost_m);
  EXPECT_EQ(res.path.poses.size(), expected.path.poses.size());
}

TEST(PlanRequestHandler, CostIsThePathLengthInMetres) {
  // Open 10 x 6 map at 0.5 m: (0, 0) to (5, 5) is five diagonal steps, 5 * sqrt(2) * 0.5 m; a step count
  // (2.5 m) or a length in cells (7.07) is wrong.
  auto open = makeMap();
  std::fill(open->data.begin(), open->data.end(), 0);
  PlanRequestHandler handler;
  ASSERT_TRUE(handler.setMap(open, nullptr));
  PlanPath::Response res;
  handler.handle(request(wx(0), wy(0), wx(5), wy(5)), &res);
  ASSERT_EQ(res.status, PlanPath::Response::OK) << res.message;
  EXPECT_NEAR(res.cost_m, 5 * std::sqrt(2.0) * 0.5, 1e-9);
  EXPECT_EQ(res.path.poses.size(), 6u);
  // Straight along a row: 9 cells of 0.5 m.
  handler.handle(request(wx(0), wy(2), wx(9), wy(2)), &res);
  ASSERT_EQ(res.status, PlanPath::Response::OK) << res.message;
  EXPECT_NEAR(res.cost_m, 4.5, 1e-9);
  EXPECT_GT(res.planning_time_s, 0.0) << "planning time is measured";
}

TEST(PlanRequestHandler, PlannerOptionsReachTheCore) {
  // Occupancy 60 between start and goal, and unknown cells in a second row.
  auto map = makeMap();
  std::fill(map->data.begin(), map->data.end(), 100);
  for (int x = 0; x < 10; ++x) map->data[1 * 10 + x] = (x == 5) ? 60 : 0;
  for (int x = 0; x < 10; ++x) map->data[3 * 10 + x] = (x == 5) ? -1 : 0;
  PlanPath::Response res;
  PlannerOptions options;
  PlanRequestHandler strict(options);  // lethal 50: 60 blocks
  ASSERT_TRUE(strict.setMap(map, nullptr));
  strict.handle(request(wx(0), wy(1), wx(9), wy(1)), &res);
  EXPECT_EQ(res.status, PlanPath::Response::NO_PATH) << res.message;
  options.lethal_threshold = 61;  // 60 passes
  PlanRequestHandler lenient(options);
  ASSERT_TRUE(lenient.setMap(map, nullptr));
  lenient.handle(request(wx(0), wy(1), wx(9), wy(1)), &res);
  EXPECT_EQ(res.status, PlanPath::Response::OK) << res.message;
  EXPECT_NEAR(res.cost_m, 4.5, 1e-9);
  strict.handle(request(wx(0), wy(3), wx(9), wy(3)), &res);
  EXPECT_EQ(res.status, PlanPath::Response::NO_PATH) << "unknown cells block by default";
  options.unknown_is_obstacle = false;
  PlanRequestHandler explorer(options);
  ASSERT_TRUE(explorer.setMap(map, nullptr));
  explorer.handle(request(wx(0), wy(3), wx(9), wy(3)), &res);
  EXPECT_EQ(res.status, PlanPath::Response::OK) << res.message;
}

TEST(PlanRequestHandler, InflationInMetresBecomesCellsAtTheMapsResolution) {
  // Cell (3, 0) is one cell (0.5 m) from the wall: inside a 0.6 m robot radius (1.2 cells), outside 0.4 m.
  PlanPath::Response res;
  InflationParams wide;
  wide.robot_radius_m = 0.6;
  PlanRequestHandler blocked(PlannerOptions(), 0, wide);
  ASSERT_TRUE(blocked.setMap(makeMap(), nullptr));
  blocked.handle(request(wx(3), wy(0), wx(0), wy(0)), &res);
  EXPECT_EQ(res.status, PlanPath::Response::START_BLOCKED) << res.message;
  InflationParams narrow;
  narrow.robot_radius_m = 0.4;
  PlanRequestHandler clear(PlannerOptions(), 0, narrow);
  ASSERT_TRUE(clear.setMap(makeMap(), nullptr));
  clear.handle(request(wx(3), wy(0), wx(0), wy(0)), &res);
  EXPECT_EQ(res.status, PlanPath::Response::OK) << res.message;
}

TEST(PlanRequestHandler, PathPosesHaveUnitQuaternionsFacingAlongThePath) {
  PlanRequestHandler handler;
  ASSERT_TRUE(handler.setMap(makeMap(), nullptr));
  auto req = request(wx(1), wy(0), wx(8), wy(0));
  req.start.pose.orientation.w = 0.0;  // a caller that leaves both ends' orientation zero
  req.goal.pose.orientation.w = 0.0;
  PlanPath::Response res;
  handler.handle(req, &res);
  ASSERT_EQ(res.status, PlanPath::Response::OK) << res.message;
  const auto& poses = res.path.poses;
  ASSERT_GE(poses.size(), 3u);
  for (std::size_t k = 1; k + 1 < poses.size(); ++k) {
    const auto& q = poses[k].pose.orientation;
    EXPECT_NEAR(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w, 1.0, 1e-12) << "pose " << k;
    const double yaw = 2.0 * std::atan2(q.z, q.w);
    const double dx = poses[k + 1].pose.position.x - poses[k].pose.position.x;
    const double dy = poses[k + 1].pose.position.y - poses[k].pose.position.y;
    EXPECT_NEAR(std::remainder(yaw - std::atan2(dy, dx), 2 * M_PI), 0.0, 1e-9) << "pose " << k;
  }
  // The ends stay the caller's poses.
  EXPECT_EQ(poses.front().pose, req.start.pose);
  EXPECT_EQ(poses.back().pose, req.goal.pose);
}

TEST(PlanRequestHandler, ToleranceFallbackEndsInTheCellReachedNotInTheObstacle) {
  PlanRequestHandler handler;
  ASSERT_TRUE(handler.setMap(makeMap(), nullptr));
  auto req = request(wx(1), wy(1), wx(4), wy(1) + 0.1);  // goal inside the wall
  req.tolerance = 0.5f;                                  // one cell: (3, 1) is the nearest free cell
  PlanPath::Response res;
  handler.handle(req, &res);
  ASSERT_EQ(res.status, PlanPath::Response::OK) << res.message;
  const auto& last = res.path.poses.back().pose;
  EXPECT_DOUBLE_EQ(last.position.x, wx(3));
  EXPECT_DOUBLE_EQ(last.position.y, wy(1));
  EXPECT_NE(last, req.goal.pose);
  EXPECT_NEAR(res.cost_m, 1.0, 1e-9);
}

TEST(PlanRequestHandler, RefusesMapsAboveTheCellLimit) {
  PlanRequestHandler handler(PlannerOptions(), 59);
  std::string error;
  EXPECT_FALSE(handler.setMap(makeMap(), &error));
  EXPECT_NE(error.find("exceeds the limit of 59 cells"), std::string::npos) << error;
  PlanRequestHandler roomy(PlannerOptions(), 60);
  EXPECT_TRUE(roomy.setMap(makeMap(), &error));
}

TEST(PlanRequestHandler, PlansAroundTheWallInWorldCoordinates) {
  PlanRequestHandler handler;
  ASSERT_TRUE(handler.setMap(makeMap(), nullptr));
  PlanPath::Response res;
  handler.handle(request(wx(1), wy(0), wx(8), wy(0)), &res);
  ASSERT_EQ(res.status, PlanPath::Response::OK) << res.message;
  EXPECT_EQ(res.path.header.frame_id, "map");
  EXPECT_EQ(res.map_stamp, ros::Time(42, 0));
  ASSERT_GE(res.path.poses.size(), 2u);
  EXPECT_DOUBLE_EQ(res.path.poses.front().pose.position.x, wx(1));
  EXPECT_DOUBLE_EQ(res.path.poses.back().pose.position.x, wx(8));
  // Around the wall through the gap at y = 5: every pose with x in the wall column is in the gap row.
  bool through_gap = false;
  for (const auto& p : res.path.poses) {
    if (std::fabs(p.pose.position.x - wx(4)) < 1e-9) {
      EXPECT_NEAR(p.pose.position.y, wy(5), 1e-9);
      through_gap = true;
    }
  }
  EXPECT_TRUE(through_gap);
  // (1, 0) to (3, 5): 2 diagonals and 3 straight; through the gap (3, 5) -> (4, 5) -> (5, 5), since no
  // diagonal may cut the wall's corner; (5, 5) to (8, 0): 3 diagonals and 2 straight. In metres.
  EXPECT_NEAR(res.cost_m, (7.0 + 5.0 * std::sqrt(2.0)) * 0.5, 1e-9);
  EXPECT_GT(res.expansions, 0u);
  EXPECT_GT(res.planning_time_s, 0.0);
}

TEST(PlanRequestHandler, ClearStatusesForBadRequests) {
  PlanRequestHandler handler;
  PlanPath::Response res;
  handler.handle(request(wx(1), wy(1), wx(2), wy(1)), &res);
  EXPECT_EQ(res.status, PlanPath::Response::NO_MAP);
  EXPECT_NE(res.message.find("no map"), std::string::npos);

  ASSERT_TRUE(handler.setMap(makeMap(), nullptr));
  handler.handle(request(wx(1), wy(1), wx(2), wy(1), "odom"), &res);
  EXPECT_EQ(res.status, PlanPath::Response::BAD_FRAME);
  EXPECT_NE(res.message.find("odom"), std::string::npos);
  handler.handle(request(wx(1), wy(1), wx(2), wy(1), "/map"), &res);
  EXPECT_EQ(res.status, PlanPath::Response::OK) << "a leading slash names the same frame";
  handler.handle(request(wx(1), wy(1), wx(2), wy(1), ""), &res);
  EXPECT_EQ(res.status, PlanPath::Response::OK) << "an empty frame means the map frame";

  handler.handle(request(-2.1, wy(1), wx(2), wy(1)), &res);
  EXPECT_EQ(res.status, PlanPath::Response::START_OFF_MAP);
  handler.handle(request(wx(1), wy(1), wx(2), 4.0 + 1e-6), &res);
  EXPECT_EQ(res.status, PlanPath::Response::GOAL_OFF_MAP);
  handler.handle(request(wx(4), wy(1), wx(2), wy(1)), &res);
  EXPECT_EQ(res.status, PlanPath::Response::START_BLOCKED);
  handler.handle(request(wx(1), wy(1), wx(4), wy(0)), &res);
  EXPECT_EQ(res.status, PlanPath::Response::GOAL_BLOCKED);
  auto req = request(wx(1), wy(1), wx(4), wy(0));
  req.tolerance = 0.5f;  // one cell: (3, 0) and (5, 0) are free
  handler.handle(req, &res);
  EXPECT_EQ(res.status, PlanPath::Response::OK) << res.message;
  req.tolerance = -1.0f;
  handler.handle(req, &res);
  EXPECT_EQ(res.status, PlanPath::Response::INVALID_REQUEST);
  handler.handle(request(NAN, wy(1), wx(2), wy(1)), &res);
  EXPECT_EQ(res.status, PlanPath::Response::INVALID_REQUEST);
  EXPECT_TRUE(res.path.poses.empty());

  auto closed = makeMap();
  closed->data[5 * 10 + 4] = 100;  // close the gap
  ASSERT_TRUE(handler.setMap(closed, nullptr));
  handler.handle(request(wx(1), wy(0), wx(8), wy(0)), &res);
  EXPECT_EQ(res.status, PlanPath::Response::NO_PATH);
  EXPECT_TRUE(res.path.poses.empty());
}

TEST(PlanRequestHandler, RejectsMalformedMapsAndKeepsThePrevious) {
  PlanRequestHandler handler;
  auto bad = makeMap();
  bad->data.resize(59);
  std::string error;
  EXPECT_FALSE(handler.setMap(bad, &error));
  EXPECT_NE(error.find("59 cells"), std::string::npos) << error;
  PlanPath::Response res;
  handler.handle(request(wx(1), wy(1), wx(2), wy(1)), &res);
  EXPECT_EQ(res.status, PlanPath::Response::NO_MAP);
  EXPECT_NE(res.message.find("59 cells"), std::string::npos) << "NO_MAP says why the map was rejected";

  ASSERT_TRUE(handler.setMap(makeMap(), nullptr));
  auto zero = makeMap();
  zero->info.resolution = 0.0f;
  EXPECT_FALSE(handler.setMap(zero, &error));
  auto empty = makeMap();
  empty->info.width = 0;
  empty->data.clear();
  EXPECT_FALSE(handler.setMap(empty, &error));
  auto twisted = makeMap();
  twisted->info.origin.orientation.z = NAN;
  EXPECT_FALSE(handler.setMap(twisted, &error));
  EXPECT_NE(error.find("origin is not finite"), std::string::npos) << error;
  handler.handle(request(wx(1), wy(1), wx(2), wy(1)), &res);
  EXPECT_EQ(res.status, PlanPath::Response::OK) << "the last good map keeps serving";
  handler.handle(request(1e308, wy(1), wx(2), wy(1)), &res);
  EXPECT_EQ(res.status, PlanPath::Response::START_OFF_MAP) << "a huge finite coordinate is off the map";
}

TEST(PlanRequestHandler, SequentialRequestsOnManyServingThreadsShareOnePlanner) {
  // A robot asks one plan at a time, and the node's serving threads take turns: one planner's buffers serve them
  // all (a planner per thread paged in buffers for each, #30), a second only for a plan beside another.
  PlanRequestHandler handler;
  ASSERT_TRUE(handler.setMap(makeMap(), nullptr));
  for (int k = 0; k < 4; ++k) {
    std::thread([&] {
      PlanPath::Response res;
      handler.handle(request(wx(1), wy(0), wx(8), wy(0)), &res);
      EXPECT_EQ(res.status, PlanPath::Response::OK) << res.message;
    }).join();
  }
  EXPECT_EQ(handler.planners(), 1u);
}

int main(int argc, char** argv) {
  ros::Time::init();  // Path stamps use ros::Time::now(); no master needed
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}

TEST(PlanRequestHandler, ACancelledPlanAnswersCancelledWithoutAPath) {
  PlanRequestHandler handler;
  ASSERT_TRUE(handler.setMap(makeMap(), nullptr));
  std::atomic<bool> cancel{true};
  PlanPath::Response res;
  handler.handle(request(wx(0), wy(0), wx(9), wy(0)), &res, &cancel);
  EXPECT_EQ(res.status, PlanPath::Response::CANCELLED) << res.message;
  EXPECT_TRUE(res.path.poses.empty());
  cancel = false;
  handler.handle(request(wx(0), wy(0), wx(9), wy(0)), &res, &cancel);
  EXPECT_EQ(res.status, PlanPath::Response::OK) << res.message;
}
