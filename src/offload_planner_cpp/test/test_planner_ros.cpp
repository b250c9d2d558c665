// The ROS request handler without a master: world/cell conversion, frames, malformed maps, statuses.
#include <gtest/gtest.h>

#include <cmath>

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

TEST(MapGeometry, ReadsYawFromMapMetaData) {
  nav_msgs::MapMetaData info;
  info.origin.orientation.z = std::sin(0.35);  // yaw 0.7 about z
  info.origin.orientation.w = std::cos(0.35);
  info.origin.position.x = 1.5;
  info.origin.position.y = -2.5;
  info.resolution = 0.1f;
  const MapGeometry g = geometryOf(info);
  EXPECT_NEAR(g.origin_yaw, 0.7, 1e-9);
  EXPECT_DOUBLE_EQ(g.origin_x, 1.5);
  EXPECT_DOUBLE_EQ(g.origin_y, -2.5);
  EXPECT_NEAR(g.resolution, 0.1, 1e-7);
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
  // 4 cells up, through the gap, 4 down: cost in metres follows the resolution.
  EXPECT_GT(res.cost_m, 7 * 0.5);
  EXPECT_GT(res.expansions, 0u);
  EXPECT_GE(res.planning_time_s, 0.0);
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

int main(int argc, char** argv) {
  ros::Time::init();  // Path stamps use ros::Time::now(); no master needed
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
