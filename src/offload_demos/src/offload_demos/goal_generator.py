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
from nav_msgs.msg import MapMetaData, OccupancyGrid
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
    scenario: str = ""
    """a bench-policies scenario file (offload_demos.scenario) whose map list this node publishes and follows: each
    map for its requests, cycled, the pause before a new map's first request in the open-loop schedule; "": the
    map topic's one map."""


PARAMETERS = {name: (GoalGeneratorConfig, name) for name in GoalGeneratorConfig.__dataclass_fields__}


def pose(frame_id: str, xy) -> PoseStamped:
    msg = PoseStamped()
    msg.header.frame_id = frame_id
    msg.header.stamp = rospy.Time.now()
    msg.pose.position.x, msg.pose.position.y = xy
    msg.pose.orientation.w = 1.0
    return msg


class GoalTarget:
    """One map's goal draws: its frame, the seeded sampler over its start's reachable free cells, the start."""

    def __init__(self, frame, sampler: GoalSampler, start_xy, frame_id: str):
        self.frame, self.sampler, self.start_xy, self.frame_id = frame, sampler, start_xy, frame_id


def goal_target(grid_msg, config: GoalGeneratorConfig, index: int = 0) -> GoalTarget:
    """The goal draws on one map (ValueError when it is unusable). Map `index` of a scenario draws from its own
    seeded stream, so each map's goals are the same in every run whatever the other maps are."""
    info = grid_msg.info
    q = info.origin.orientation
    checked, frame = check_map(info.width, info.height, len(grid_msg.data), info.resolution,
                               info.origin.position.x, info.origin.position.y, (q.x, q.y, q.z, q.w))
    if not checked.ok:
        raise ValueError(f"the map is unusable: {checked.message}")
    grid = np.ascontiguousarray(grid_msg.data, dtype=np.int8).reshape(info.height, info.width)
    free = free_cells(grid, config.lethal_threshold, config.unknown_is_obstacle)
    start_cell = None
    if math.isfinite(config.start_x) and math.isfinite(config.start_y):
        start_cell = frame.world_to_cell(config.start_x, config.start_y)
        if start_cell is None:
            raise ValueError(f"~start_x, ~start_y ({config.start_x}, {config.start_y}) m is off the map")
    start_cell = default_start_cell(free, start_cell)
    seed = config.seed if index == 0 else [config.seed, index]
    sampler = GoalSampler(free, start_cell, seed, config.min_distance_m / info.resolution)
    return GoalTarget(frame, sampler, frame.cell_to_world(*start_cell), grid_msg.header.frame_id or "map")


def scenario_maps(config: GoalGeneratorConfig):
    """The scenario and its maps as OccupancyGrid messages ((None, []) without a scenario or a map list)."""
    if not config.scenario:
        return None, []
    from offload_demos.scenario import load_scenario
    from offload_planner_cpp.maps import load_map
    from offload_planner_cpp.nodes.map_publisher import to_message

    scenario = load_scenario(config.scenario)
    return scenario, [to_message(load_map(path), "map", rospy.Time.now()) for path, _ in scenario.maps]


def publish_map(publishers, msg) -> float:
    """Publish a scenario's map as in force from now (a fresh load time, which the learner's stale-map check
    compares the planners' answers with); the CLOCK_MONOTONIC second it went out."""
    map_pub, meta_pub = publishers
    msg.header.stamp = msg.info.map_load_time = rospy.Time.now()
    meta_pub.publish(msg.info)
    map_pub.publish(msg)
    return time.monotonic()


def main():
    """Goal generator node: its parameters are GoalGeneratorConfig's fields.
    Topics: subscribes map (nav_msgs/OccupancyGrid, once); publishes ~goal (geometry_msgs/PoseStamped); with a
    ~scenario's map list, publishes map and map_metadata (latched) instead of subscribing.
    """
    rospy.init_node("goal_generator")
    config = GoalGeneratorConfig(**params.read(lambda name, default: rospy.get_param("~" + name, default),
                                               PARAMETERS))
    service, count, period_s, rate_hz = config.service, config.count, config.period_s, config.rate_hz
    epoch = config.epoch
    try:
        if not (math.isfinite(rate_hz) and rate_hz >= 0 and math.isfinite(epoch) and epoch >= 0):
            raise ValueError(f"~rate_hz and ~epoch must be finite and >= 0, got {rate_hz}, {epoch}")
        scenario, maps = scenario_maps(config)
        targets = [goal_target(grid_msg, config, k) for k, grid_msg in enumerate(maps)] or \
            [goal_target(rospy.wait_for_message("map", numpy_msg(OccupancyGrid), timeout=config.map_wait_s), config)]
        publishers = None
        if maps:   # this node is the map's publisher (the launch's map_publisher is off), latched as map_publisher's
            publishers = (rospy.Publisher("map", numpy_msg(OccupancyGrid), queue_size=1, latch=True),
                          rospy.Publisher("map_metadata", MapMetaData, queue_size=1, latch=True))
            publish_map(publishers, maps[0])    # before the service: the learner serves once it has a map
        rospy.wait_for_service(service, timeout=config.service_wait_s)
    except (ValueError, rospy.ROSException) as error:
        rospy.logfatal("%s", error)
        raise SystemExit(1) from None
    for target in targets:
        rospy.loginfo("goal generator: %s requests from (%.2f, %.2f) to random goals among %d reachable cells -> %s",
                      count or "unbounded", *target.start_xy, target.sampler.reachable_cells, service)
    current = 0
    goal_pub = rospy.Publisher("~goal", PoseStamped, queue_size=10, latch=True)
    plan = rospy.ServiceProxy(service, PlanPath, persistent=True)
    tolerance = config.tolerance
    sent = delivered = 0
    began = epoch if epoch > 0 else time.monotonic()
    offsets = scenario.request_times(count, rate_hz) if maps and rate_hz > 0 and count > 0 else None
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
            index = scenario.map_index(sent) if maps else 0
            if index != current:
                # Half-way through the pause: the previous request's slower side (a probe's, a hedge's) has had
                # time to start on the map it was drawn on, and the planners have the rest to take the new one.
                if offsets is not None:
                    wait_until(began + offsets[sent] - scenario.map_settle_s / 2)
                current = index
                switched = publish_map(publishers, maps[index])
                if offsets is None:    # paced by the answers: the pause alone
                    wait_until(switched + scenario.map_settle_s / 2)
            if offsets is not None:
                wait_until(began + offsets[sent])
            else:
                wait_until(began + sent / rate_hz if rate_hz > 0 else began)
        except rospy.ROSInterruptException:
            break
        target = targets[current]
        frame_id, start_xy = target.frame_id, target.start_xy
        goal = pose(frame_id, target.frame.cell_to_world(*target.sampler.draw()))
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
