// World <-> cell conversion for a grid whose cell (0, 0) has its lower-left corner at the origin pose,
// as in nav_msgs/MapMetaData. ROS-free so it is tested without a master.
#pragma once

#include <cmath>

#include "offload_planner_cpp/dijkstra.h"

namespace offload_planner {

// Heading of a quaternion about z (the map plane), as tf2::getYaw computes it. Both arguments of atan2
// scale with the squared norm, so a quaternion that is not of unit length gives the yaw of its
// normalised self: (0, 0, 10, 10) is 90 degrees. The caller rejects zero and non-finite quaternions.
inline double yawOf(double qx, double qy, double qz, double qw) {
  return std::atan2(2.0 * (qx * qy + qw * qz), qw * qw + qx * qx - qy * qy - qz * qz);
}

struct MapGeometry {
  double resolution = 1.0;  // metres per cell
  double origin_x = 0.0;    // metres, map frame
  double origin_y = 0.0;
  double origin_yaw = 0.0;  // radians; map_server writes 0 but the message allows any
  int width = 0;
  int height = 0;

  // Cell containing the world point; returns false when it lies off the grid.
  bool worldToCell(double wx, double wy, Cell* cell) const {
    const double dx = wx - origin_x;
    const double dy = wy - origin_y;
    const double c = std::cos(origin_yaw);
    const double s = std::sin(origin_yaw);
    const double gx = std::floor((c * dx + s * dy) / resolution);
    const double gy = std::floor((-s * dx + c * dy) / resolution);
    if (!(gx >= 0 && gy >= 0 && gx < width && gy < height)) return false;
    cell->x = static_cast<int>(gx);
    cell->y = static_cast<int>(gy);
    return true;
  }

  // World coordinates of the cell's centre.
  void cellToWorld(Cell cell, double* wx, double* wy) const {
    cellToWorld(cell, std::cos(origin_yaw), std::sin(origin_yaw), wx, wy);
  }
  // The same with cos and sin of origin_yaw given, for a caller converting many cells (pathPoses).
  void cellToWorld(Cell cell, double c, double s, double* wx, double* wy) const {
    const double gx = (cell.x + 0.5) * resolution;
    const double gy = (cell.y + 0.5) * resolution;
    *wx = origin_x + c * gx - s * gy;
    *wy = origin_y + s * gx + c * gy;
  }
};

}  // namespace offload_planner
