"""World <-> cell conversion and map validation, a line-for-line port of the local planner node's
map_geometry.h and validateMap() (planner_ros.cpp), so the cloud bridge answers exactly as the local
node does for the same request. ROS-free; messages are formatted as C++ iostreams print doubles (%g)."""
import math
from dataclasses import dataclass
from typing import Optional, Tuple


def yaw_of(qx: float, qy: float, qz: float, qw: float) -> float:
    """Heading of a quaternion about z (the map plane), as tf2::getYaw computes it."""
    return math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))


def fmt(value: float) -> str:
    """A double as `std::ostream << value` prints it by default."""
    return f"{value:g}"


@dataclass(frozen=True)
class MapGeometry:
    resolution: float = 1.0   # metres per cell
    origin_x: float = 0.0     # metres, map frame
    origin_y: float = 0.0
    origin_yaw: float = 0.0   # radians
    width: int = 0
    height: int = 0

    def world_to_cell(self, wx: float, wy: float) -> Optional[Tuple[int, int]]:
        """Cell (x, y) containing the world point, or None off the grid."""
        dx = wx - self.origin_x
        dy = wy - self.origin_y
        c = math.cos(self.origin_yaw)
        s = math.sin(self.origin_yaw)
        fx = (c * dx + s * dy) / self.resolution
        fy = (-s * dx + c * dy) / self.resolution
        # Bounds first, on the floats: floor(f) >= 0 iff f >= 0 and floor(f) < n iff f < n, so this is the
        # C++ test, and NaN or inf (a huge finite point, e.g. 1e308 m at 0.05 m/cell) fails it as there
        # instead of overflowing math.floor.
        if not (0.0 <= fx < self.width and 0.0 <= fy < self.height):
            return None
        return int(math.floor(fx)), int(math.floor(fy))

    def cell_to_world(self, x: int, y: int) -> Tuple[float, float]:
        """World coordinates of the cell's centre."""
        gx = (x + 0.5) * self.resolution
        gy = (y + 0.5) * self.resolution
        c = math.cos(self.origin_yaw)
        s = math.sin(self.origin_yaw)
        return self.origin_x + c * gx - s * gy, self.origin_y + s * gx + c * gy

    def cells_to_world(self, path):
        """World centres of an N x 2 array of cells, vectorised for long paths."""
        import numpy as np
        g = (np.asarray(path, dtype=np.float64) + 0.5) * self.resolution
        c = math.cos(self.origin_yaw)
        s = math.sin(self.origin_yaw)
        return (self.origin_x + c * g[:, 0] - s * g[:, 1], self.origin_y + s * g[:, 0] + c * g[:, 1])


def validate_map(width: int, height: int, data_size: int, resolution: float, origin_x: float,
                 origin_y: float, orientation: Tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)) -> str:
    """Empty when the map is usable, else why not (the same checks and wording as validateMap()).
    `orientation` is the origin quaternion (x, y, z, w)."""
    if width == 0 or height == 0:
        return f"map is empty ({width} x {height})"
    if width * height != data_size:
        return f"map data has {data_size} cells but {width} x {height} = {width * height} were declared"
    if not (resolution > 0.0) or not math.isfinite(resolution):
        return f"map resolution {fmt(resolution)} is not a positive number"
    if not all(math.isfinite(v) for v in (origin_x, origin_y, *orientation)):
        return "map origin is not finite"
    if width > 100000 or height > 100000:
        return f"map of {width} x {height} cells is larger than the planner accepts"
    return ""


def strip_slash(frame: str) -> str:
    return frame[1:] if frame.startswith("/") else frame


def in_map_frame(frame: str, map_frame: str) -> bool:
    """An empty frame means the map frame, as RViz's and move_base's callers often leave it."""
    return not frame or strip_slash(frame) == strip_slash(map_frame)
