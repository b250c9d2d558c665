"""map_publisher: publishes a map file as a latched nav_msgs/OccupancyGrid, like map_server, for the
planner nodes, the cloud bridge and the demo (Debian ships no map_server).

Parameters: ~map (required: a map_server `.yaml` or a MovingAI `.map` file) and MapPublisherConfig's fields.

Topics:
    map (nav_msgs/OccupancyGrid, latched), map_metadata (nav_msgs/MapMetaData, latched),
    /tf_static (tf2_msgs/TFMessage, latched; only with ~static_child_frame).
"""
import math
from dataclasses import dataclass

import numpy as np
import rospy
import tf2_ros
from geometry_msgs.msg import TransformStamped
from nav_msgs.msg import MapMetaData, OccupancyGrid
from rospy.numpy_msg import numpy_msg

from offload_planner_cpp.maps import MapFormatError, OccupancyMap, load_map

NumpyOccupancyGrid = numpy_msg(OccupancyGrid)


@dataclass(frozen=True)
class MapPublisherConfig:
    """The node's parameters (~name) beside ~map, and their defaults."""
    frame_id: str = "map"
    """frame of the published map."""
    movingai_resolution: float = 0.05
    """metres per cell for MovingAI maps, which have none."""
    static_child_frame: str = ""
    """when set, also broadcasts an identity transform from ~frame_id to this frame on /tf_static, so the map
    frame exists in TF (RViz's fixed frame) where nothing localises the robot (the demo). Leave it empty on a
    robot whose localisation publishes map -> odom."""


def to_message(occupancy: OccupancyMap, frame_id: str, stamp) -> NumpyOccupancyGrid:
    """The map as an OccupancyGrid whose data stays a numpy int8 array (serialised without Python ints)."""
    msg = NumpyOccupancyGrid()
    msg.header.frame_id = frame_id
    msg.header.stamp = stamp
    info = msg.info
    info.map_load_time = stamp
    info.resolution = occupancy.resolution
    info.width, info.height = occupancy.width, occupancy.height
    info.origin.position.x, info.origin.position.y = occupancy.origin_x, occupancy.origin_y
    info.origin.orientation.z = math.sin(occupancy.origin_yaw / 2.0)
    info.origin.orientation.w = math.cos(occupancy.origin_yaw / 2.0)
    msg.data = np.ascontiguousarray(occupancy.grid, dtype=np.int8).ravel()
    return msg


def identity_transform(parent: str, child: str, stamp) -> TransformStamped:
    transform = TransformStamped()
    transform.header.frame_id = parent
    transform.header.stamp = stamp
    transform.child_frame_id = child
    transform.transform.rotation.w = 1.0
    return transform


def main():
    rospy.init_node("map_publisher")
    path = str(rospy.get_param("~map", None) or "")
    frame_id = str(rospy.get_param("~frame_id", MapPublisherConfig.frame_id))
    static_child_frame = str(rospy.get_param("~static_child_frame", MapPublisherConfig.static_child_frame))
    if not path:
        rospy.logfatal("~map is required: a map_server .yaml or a MovingAI .map file")
        raise SystemExit(2)
    try:
        occupancy = load_map(path)
    except (MapFormatError, OSError) as error:
        rospy.logfatal("cannot load map: %s", error)
        raise SystemExit(2)
    if path.endswith(".map"):
        resolution = float(rospy.get_param("~movingai_resolution", MapPublisherConfig.movingai_resolution))
        occupancy = OccupancyMap(occupancy.grid, resolution, name=occupancy.name)
    msg = to_message(occupancy, frame_id, rospy.Time.now())
    map_pub = rospy.Publisher("map", NumpyOccupancyGrid, queue_size=1, latch=True)
    meta_pub = rospy.Publisher("map_metadata", MapMetaData, queue_size=1, latch=True)
    meta_pub.publish(msg.info)
    map_pub.publish(msg)
    if static_child_frame:
        broadcaster = tf2_ros.StaticTransformBroadcaster()
        broadcaster.sendTransform(identity_transform(frame_id, static_child_frame, msg.header.stamp))
    rospy.loginfo("published %s: %d x %d cells at %.3f m in frame '%s'", path, occupancy.width, occupancy.height,
                  occupancy.resolution, frame_id)
    rospy.spin()
