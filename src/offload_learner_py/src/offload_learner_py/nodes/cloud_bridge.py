"""rospy node around bridge.CloudBridge: the robot's door to the cloud planner. It serves the same
offload_msgs/PlanPath service as the local planner node, so a caller can use either."""
import threading
import time
from dataclasses import dataclass

import rospy
import zmq
from genpy import Time
from nav_msgs.msg import OccupancyGrid, Path
from nav_msgs.srv import GetPlan, GetPlanResponse
from offload_msgs.msg import LinkLatency, PlanTiming
from offload_msgs.srv import PlanPath, PlanPathResponse
from rospy.numpy_msg import numpy_msg

from offload_cloud.bridge import BridgeConfig, BridgeResult, CloudBridge, StampedPose
from offload_cloud.gc_pauses import freeze_startup_heap
from offload_learner_py.nodes import params
from offload_learner_py.nodes.bridge_reconfigure import PlannerUpdates
from offload_learner_py.nodes.diagnostics import NodeDiagnostics
from offload_learner_py.online.health import LinkHealth
from offload_learner_py.nodes.path_wire import (WirePath, WirePlanPathResponse, path_of_rows, pose_count,
                                                pose_row_prefix)
from offload_planner_cpp import options_table, validate_options

# A parameter's Python type by the type of its row in the core's options table.
PARAMETER_TYPES = {"bool": bool, "int": int, "float": float, "algorithm": str}


def stamped_pose(msg) -> StampedPose:
    p, q = msg.pose.position, msg.pose.orientation
    return StampedPose(msg.header.frame_id, p.x, p.y, p.z, (q.x, q.y, q.z, q.w))


@dataclass(frozen=True)
class BridgeNodeConfig:
    """The node's own settings beside BridgeConfig's."""
    heartbeat_period_s: float = 0.5
    """ping period for ~latency (b_t fresh for the learner); 0 disables the heartbeat."""
    planner_name: str = "cloud"
    """the `planner` field of ~timing."""
    planner_updates: str = "/planner/parameter_updates"
    """the local planner's dynamic_reconfigure updates, whose planner options the bridge follows ("": its own)."""


# ~name -> (dataclass, field), its default the field's, for the parameters beside the planner options (those
# are the core's options table's node parameters, read by its names, types and defaults: planner_defaults()).
# ~endpoint has no default (required).
PARAMETERS = {name: (BridgeConfig, name) for name in (
    "keys_dir", "insecure", "timeout_s", "retries", "heartbeat_timeout_s", "max_map_cells")}
NODE_PARAMETERS = {name: (BridgeNodeConfig, name) for name in BridgeNodeConfig.__dataclass_fields__}


def _get(name: str, default):
    return rospy.get_param("~" + name, default)


def planner_defaults() -> dict:
    """The planner options the node reads, by name, with the core's defaults."""
    return {row["name"]: row["default"] for row in options_table() if row["node_parameter"]}


def read_parameters() -> BridgeConfig:
    endpoint = rospy.get_param("~endpoint", None)
    if not endpoint:
        raise ValueError("~endpoint is required, e.g. tcp://cloud.example.org:5555")
    values = params.read(_get, PARAMETERS)
    values["keys_dir"] = values["keys_dir"] or None
    if not values["keys_dir"] and not values["insecure"]:
        raise ValueError("~keys_dir is required (CURVE is on by default); set ~insecure true for plaintext")
    # The planner options: the core table's node parameters, by their names, types and defaults, as the
    # local planner node reads them.
    planner = {row["name"]: PARAMETER_TYPES[row["type"]](_get(row["name"], row["default"]))
               for row in options_table() if row["node_parameter"]}
    config = BridgeConfig(endpoint=str(endpoint), **values, **BridgeConfig.planner_fields(planner))
    try:
        validate_options(**config.planner_parameters())   # the core's checks, the core's words
    except ValueError as error:
        raise ValueError(f"~{error}") from None
    if config.timeout_s <= 0 or config.retries < 0 or config.heartbeat_timeout_s <= 0:
        raise ValueError("~timeout_s and ~heartbeat_timeout_s must be > 0 and ~retries >= 0")
    return config


def read_node_parameters() -> BridgeNodeConfig:
    return BridgeNodeConfig(**params.read(_get, NODE_PARAMETERS))


def plan_response(result: BridgeResult, stamp=None) -> WirePlanPathResponse:
    """The PlanPath response of a bridge result: its path from the result's pose rows (bridge.plan(row_prefix=
    row_prefix_now): stamped and framed by their prefix), or else from its poses, stamped `stamp`. On the bridge's
    path of every cloud plan, where each call meets a cold cache (#30's bridge CPU bar): the path is written by the
    core in one pass, not a genpy PoseStamped per pose, and the fields are set directly, not through genpy's keyword
    __init__, which checks every keyword and makes a default Path, Header and Times only to drop them."""
    res = WirePlanPathResponse.__new__(WirePlanPathResponse)
    res.status = status = int(result.status)
    if status != PlanPathResponse.OK:
        res.path = Path()
    elif result.pose_rows:
        res.path = path_of_rows(result.pose_row_prefix, result.pose_rows)
    else:
        res.path = WirePath.from_poses(result.frame_id, stamp, result.poses)
    res.message, res.planning_time_s, res.expansions = result.message, result.planning_time_s, result.expansions
    res.cost_m, res.cpu_s = result.cost_m, 0.0
    res.map_stamp = result.map_stamp if result.map_stamp is not None else Time()
    res.bytes_sent, res.bytes_received = result.bytes_sent, result.bytes_received
    return res


def row_prefix_now(frame_id: str) -> bytes:
    """The pose row prefix of a path stamped now (the path's poses are written when it is back from the cloud)."""
    return pose_row_prefix(rospy.Time.now(), frame_id)


class CloudBridgeNode:
    def __init__(self, config: BridgeConfig, heartbeat_period_s: float, planner_name: str, planner_updates: str = ""):
        self.bridge = CloudBridge(config)
        self.planner_updates = PlannerUpdates(self.bridge, planner_updates)   # the local planner's options, followed
        self.planner_name = planner_name
        self.heartbeat_period_s = heartbeat_period_s
        self.latency_pub = rospy.Publisher("~latency", LinkLatency, queue_size=10)
        # A deep queue: a burst of fast plans must not drop timings the learner and the bags rely on.
        self.timing_pub = rospy.Publisher("~timing", PlanTiming, queue_size=1000)
        self.path_pub = rospy.Publisher("~path", Path, queue_size=1, latch=True)
        # numpy_msg keeps the grid as one int8 array: no per-cell Python ints.
        self.map_sub = rospy.Subscriber("map", numpy_msg(OccupancyGrid), self.on_map, queue_size=1,
                                        buff_size=1 << 26)
        self.plan_srv = rospy.Service("~plan", PlanPath, self.on_plan)
        self.make_plan_srv = rospy.Service("~make_plan", GetPlan, self.on_make_plan)
        self.health = LinkHealth()
        self.diagnostics = NodeDiagnostics("cloud link", self.health.status, hardware_id=config.endpoint)
        self._stopped = threading.Event()
        self._heartbeat = threading.Thread(target=self.heartbeat_loop, name="heartbeat", daemon=True)
        self._heartbeat.start()
        rospy.on_shutdown(self.shutdown)
        rospy.loginfo("cloud bridge to %s (%s), timeout %g s, %d retries; waiting for a map on %s",
                      config.endpoint, "INSECURE" if config.insecure else "CURVE", config.timeout_s,
                      config.retries, self.map_sub.resolved_name)

    def shutdown(self) -> None:
        self._stopped.set()
        self.diagnostics.close()
        self._heartbeat.join(5.0)
        self.bridge.close()

    def on_map(self, msg) -> None:
        info = msg.info
        q = info.origin.orientation
        why = self.bridge.set_map(msg.data, info.width, info.height, info.resolution, info.origin.position.x,
                                  info.origin.position.y, (q.x, q.y, q.z, q.w), msg.header.frame_id,
                                  msg.header.stamp)
        self.health.map_refused = why or ""
        if not why:
            self.health.map_cells = info.width * info.height
        self.diagnostics.changed()
        if why:
            rospy.logerr("rejected map on %s: %s; keeping the previous map", self.map_sub.resolved_name, why)
        else:
            rospy.loginfo("map %d x %d at %.3f m/cell in frame '%s'", info.width, info.height, info.resolution,
                          msg.header.frame_id)

    def heartbeat_loop(self) -> None:
        while not self._stopped.wait(self.heartbeat_period_s) and not rospy.is_shutdown():
            measured = self.bridge.recent_round_trip(self.heartbeat_period_s)
            if measured is not None:   # a plan's answer measured the link since the last ping: ~latency has it
                reachable, round_trip_s = True, measured
            else:
                reachable, round_trip_s = self.bridge.heartbeat()
                self.publish_latency(LinkLatency.HEARTBEAT, reachable, round_trip_s)
            self.health.heartbeat(reachable, round_trip_s, pinged=measured is None)
            self.diagnostics.changed()

    def publish_latency(self, source: int, reachable: bool, round_trip_s: float) -> None:
        msg = LinkLatency(source=source, reachable=reachable, round_trip_s=round_trip_s)
        msg.header.stamp = rospy.Time.now()
        try:
            self.latency_pub.publish(msg)
        except rospy.ROSException:   # publishing during shutdown
            pass

    def serve(self, req) -> PlanPathResponse:
        started = rospy.get_time()
        cpu_started = time.thread_time()   # this service thread's CPU: the robot's cost of offloading
        result = self.bridge.plan(stamped_pose(req.start), stamped_pose(req.goal), req.tolerance, row_prefix_now)
        res = plan_response(result)
        res.cpu_s = time.thread_time() - cpu_started
        if result.link_round_trip_s is not None:
            self.publish_latency(LinkLatency.REQUEST, result.reachable, result.link_round_trip_s)
        timing = PlanTiming(planner=self.planner_name, status=res.status, planning_time_s=res.planning_time_s,
                            service_time_s=rospy.get_time() - started, expansions=res.expansions,
                            path_cells=pose_count(res.path), cost_m=res.cost_m, map_stamp=res.map_stamp)
        timing.header.stamp = rospy.Time.now()
        self.timing_pub.publish(timing)
        self.health.plan("timeout" if res.status == PlanPathResponse.CLOUD_TIMEOUT else
                         "failed" if res.status == PlanPathResponse.CLOUD_ERROR else "ok")
        if res.status == PlanPathResponse.OK:
            self.path_pub.publish(res.path)
        else:
            rospy.logwarn("plan failed (%s): %s", result.status.name, res.message)
        return res

    def on_plan(self, req) -> PlanPathResponse:
        return self.serve(req)   # failures travel in res.status so the caller always learns why

    def on_make_plan(self, req) -> GetPlanResponse:
        res = self.serve(req)
        if res.status != PlanPathResponse.OK:
            # Empty on failure, as navfn answers, but in the global frame and stamped now as navfn's is.
            snapshot = self.bridge.map
            res.path.header.frame_id = snapshot.frame_id if snapshot is not None else ""
            res.path.header.stamp = rospy.Time.now()
        return GetPlanResponse(plan=res.path)


def main():
    """Cloud bridge node.

    Parameters (private): ~endpoint (required), PARAMETERS and NODE_PARAMETERS (each defaulting to its
    field's default) and the core's planner options; the package README's table lists them.
    Topics: subscribes map (nav_msgs/OccupancyGrid) and the local planner's dynamic_reconfigure updates (the topic
    ~planner_updates names); publishes ~latency (offload_msgs/LinkLatency),
    ~timing (offload_msgs/PlanTiming), ~path (nav_msgs/Path, latched), /diagnostics (the link's status).
    Services: ~plan (offload_msgs/PlanPath), ~make_plan (nav_msgs/GetPlan).
    """
    rospy.init_node("cloud_bridge")
    try:
        config, own = read_parameters(), read_node_parameters()
        # None: the heartbeat thread waits for shutdown only.
        node = CloudBridgeNode(config, own.heartbeat_period_s if own.heartbeat_period_s > 0 else None,
                               own.planner_name, own.planner_updates)
    except (ValueError, OSError, zmq.ZMQError) as error:
        # One line naming the cause (a key file: KeyFileError names it), then exit: never a node that
        # runs without a working link.
        rospy.logfatal("%s", error)
        raise SystemExit(1) from None
    freeze_startup_heap()
    rospy.spin()
    return node


if __name__ == "__main__":
    main()
