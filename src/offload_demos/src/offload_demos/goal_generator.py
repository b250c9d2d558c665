"""goal_generator: random reachable goals, as in the paper, sent to a planner's PlanPath service (the
learner's ~plan by default) at a rate or for a count. Exits after the count, so a launch file can mark
it required and end the run."""
import math
import os
import signal
import time
from dataclasses import dataclass

import numpy as np
import rospy
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import OccupancyGrid
from offload_msgs.srv import PlanPath, PlanPathRequest, PlanPathResponse
from rospy.numpy_msg import numpy_msg

from offload_planner_cpp import free_cells
from offload_planner_cpp._core import check_map
from offload_learner_py.nodes import params
from offload_demos.goals import GoalSampler, default_start_cell


@dataclass(frozen=True)
class GoalGeneratorConfig:
    """The node's parameters (~name) and their defaults; launch/config/goal_generator.yaml holds what the demo
    overrides."""
    service: str = "/offload_learner/plan"
    """PlanPath service to call."""
    count: int = 100
    """requests to send, then exit; 0 sends until shutdown."""
    period_s: float = 0.1
    """pause between the answer to one request and the next request."""
    rate_hz: float = 0.0
    """instead, open-loop arrivals: request k is sent k / rate_hz seconds after the start, whatever the answers
    took (one still waits for the previous answer; a late one goes at once and the schedule is kept); 0 uses
    period_s."""
    epoch: float = 0.0
    """CLOCK_MONOTONIC second of the first request, shared with the run's other schedules (workload, WAN
    emulator), so with rate_hz every request meets the same moment of them in every run; 0: as soon as the map
    and the service are there."""
    seed: int = 1
    """goal draws."""
    start_x: float = math.nan
    start_y: float = math.nan
    """start in the map frame (NaN: the free cell nearest the map centre)."""
    min_distance_m: float = 0.0
    """goals at least this far from the start."""
    lethal_threshold: int = 50
    unknown_is_obstacle: bool = True
    """the planners' rules of free cells (goals only in cells they can plan to)."""
    tolerance: float = 0.0
    """PlanPath tolerance of each request."""
    map_wait_s: float = 60.0
    """how long to wait for the map."""
    service_wait_s: float = 120.0
    """how long to wait for the service."""
    end_launch_when_done: bool = False
    """after count requests, end the roslaunch that started this node (SIGINT to the parent, as Ctrl-C): the
    demo's clean end."""
    end_delay_s: float = 6.0
    """before that, time for the last outcome to be recorded."""


PARAMETERS = {name: (GoalGeneratorConfig, name) for name in GoalGeneratorConfig.__dataclass_fields__}


def pose(frame_id: str, xy) -> PoseStamped:
    msg = PoseStamped()
    msg.header.frame_id = frame_id
    msg.header.stamp = rospy.Time.now()
    msg.pose.position.x, msg.pose.position.y = xy
    msg.pose.orientation.w = 1.0
    return msg


def main():
    """Goal generator node: its parameters are GoalGeneratorConfig's fields.
    Topics: subscribes map (nav_msgs/OccupancyGrid, once); publishes ~goal (geometry_msgs/PoseStamped).
    """
    rospy.init_node("goal_generator")
    config = GoalGeneratorConfig(**params.read(lambda name, default: rospy.get_param("~" + name, default),
                                               PARAMETERS))
    service, count, period_s, rate_hz = config.service, config.count, config.period_s, config.rate_hz
    epoch = config.epoch
    try:
        if not (math.isfinite(rate_hz) and rate_hz >= 0 and math.isfinite(epoch) and epoch >= 0):
            raise ValueError(f"~rate_hz and ~epoch must be finite and >= 0, got {rate_hz}, {epoch}")
        grid_msg = rospy.wait_for_message("map", numpy_msg(OccupancyGrid), timeout=config.map_wait_s)
        info = grid_msg.info
        q = info.origin.orientation
        checked, frame = check_map(info.width, info.height, len(grid_msg.data), info.resolution,
                                   info.origin.position.x, info.origin.position.y, (q.x, q.y, q.z, q.w))
        if not checked.ok:
            raise ValueError(f"the map is unusable: {checked.message}")
        grid = np.ascontiguousarray(grid_msg.data, dtype=np.int8).reshape(info.height, info.width)
        free = free_cells(grid, config.lethal_threshold, config.unknown_is_obstacle)
        start_x, start_y = config.start_x, config.start_y
        start_cell = None
        if math.isfinite(start_x) and math.isfinite(start_y):
            start_cell = frame.world_to_cell(start_x, start_y)
            if start_cell is None:
                raise ValueError(f"~start_x, ~start_y ({start_x}, {start_y}) m is off the map")
        start_cell = default_start_cell(free, start_cell)
        sampler = GoalSampler(free, start_cell, config.seed, config.min_distance_m / info.resolution)
        rospy.wait_for_service(service, timeout=config.service_wait_s)
    except (ValueError, rospy.ROSException) as error:
        rospy.logfatal("%s", error)
        raise SystemExit(1) from None
    frame_id = grid_msg.header.frame_id or "map"
    start_xy = frame.cell_to_world(*start_cell)
    rospy.loginfo("goal generator: %s requests from (%.2f, %.2f) to random goals among %d reachable cells -> %s",
                  count or "unbounded", start_xy[0], start_xy[1], sampler.reachable_cells, service)
    goal_pub = rospy.Publisher("~goal", PoseStamped, queue_size=10, latch=True)
    plan = rospy.ServiceProxy(service, PlanPath, persistent=True)
    tolerance = config.tolerance
    sent = delivered = 0
    began = epoch if epoch > 0 else time.monotonic()
    if epoch > 0 and time.monotonic() > epoch + (1.0 / rate_hz if rate_hz > 0 else 0.0):
        rospy.logwarn("goal generator: ready %.1f s after the run's epoch: the first requests go at once to catch "
                      "up, and meet other moments of the run's schedules than in a run that started in time",
                      time.monotonic() - epoch)

    def wait_until(when: float) -> None:
        left = when - time.monotonic()
        if left > 0:
            rospy.sleep(left)
    while not rospy.is_shutdown() and (count <= 0 or sent < count):
        try:
            wait_until(began + sent / rate_hz if rate_hz > 0 else began)
        except rospy.ROSInterruptException:
            break
        goal = pose(frame_id, frame.cell_to_world(*sampler.draw()))
        goal_pub.publish(goal)
        try:
            response = plan(PlanPathRequest(start=pose(frame_id, start_xy), goal=goal, tolerance=tolerance))
            delivered += response.status == PlanPathResponse.OK
            if response.status != PlanPathResponse.OK:
                rospy.logwarn("request %d: no path (status %d): %s", sent + 1, response.status, response.message)
        except (rospy.ServiceException, rospy.ROSException) as error:
            if rospy.is_shutdown():
                break
            rospy.logwarn("request %d failed: %s; reconnecting", sent + 1, error)
            plan.close()
            plan = rospy.ServiceProxy(service, PlanPath, persistent=True)
        sent += 1
        try:
            if rate_hz <= 0 and period_s > 0:
                rospy.sleep(period_s)
        except rospy.ROSInterruptException:
            break
    rospy.loginfo("goal generator done: %d paths delivered for %d requests", delivered, sent)
    plan.close()
    if config.end_launch_when_done and not rospy.is_shutdown():
        # The last request's outcome is published once its slower side is done (up to the cloud timeout):
        # wait for it to reach the recorder before the launch goes down.
        rospy.sleep(config.end_delay_s)
        # The launch that started us (roslaunch is our parent) ends as on Ctrl-C: a clean shutdown, where a
        # `required` node that exits makes roslaunch report a death in red.
        os.kill(os.getppid(), signal.SIGINT)
        rospy.spin()   # exit when roslaunch shuts us down with the rest, not before (that would be a death)


if __name__ == "__main__":
    main()
