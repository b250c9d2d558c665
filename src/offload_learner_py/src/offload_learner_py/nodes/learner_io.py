"""The offload_learner node's ROS side that is not the node itself: the planner proxies and the PlanPath
statuses the router tells apart, the messages it publishes built from the router's and the learner's records,
the wait for the recorder, and RViz goals (a 2D Nav Goal planned from the robot's pose)."""
import json
import math
import threading
import time
from dataclasses import asdict

import rospy
from geometry_msgs.msg import PoseStamped
from std_msgs.msg import UInt64
from nav_msgs.msg import Path
from offload_msgs.msg import LearnerConfig, OffloadDecision, OffloadOutcome, TrainingStats
from offload_msgs.srv import PlanPathRequest, PlanPathResponse

from offload_learner_py.nodes.path_wire import WirePlanPath
from offload_learner_py.online.request_check import check_request
from offload_learner_py.online.router_types import Statuses

STATUSES = Statuses(ok=PlanPathResponse.OK, cloud_timeout=PlanPathResponse.CLOUD_TIMEOUT,
                    cloud_error=PlanPathResponse.CLOUD_ERROR, stale_map=PlanPathResponse.STALE_MAP,
                    cancelled=PlanPathResponse.CANCELLED,
                    refusals=(PlanPathResponse.NO_PATH, PlanPathResponse.START_BLOCKED, PlanPathResponse.GOAL_BLOCKED))


class RosLog:
    """The learner's logger, on rosout."""
    debug, info, warning, error = (staticmethod(rospy.logdebug), staticmethod(rospy.loginfo),
                                   staticmethod(rospy.logwarn), staticmethod(rospy.logerr))


class PlannerProxy:
    """Persistent connections to one planner's ~plan, one per call in flight (the router calls the cloud side
    concurrently), each reopened after any failure. Responses keep their paths serialized (path_wire): the node
    passes them on and never reads a pose."""

    def __init__(self, service: str):
        self.service = service
        self._idle = []
        self._lock = threading.Lock()

    def __call__(self, request, call_id: int = 0):
        with self._lock:
            proxy = self._idle.pop() if self._idle else None
        if proxy is None:
            proxy = rospy.ServiceProxy(self.service, WirePlanPath, persistent=True)
        # A copy: both sides of a probe get the same request object, each with its own cancel_id.
        mine = PlanPathRequest(start=request.start, goal=request.goal, tolerance=request.tolerance, cancel_id=call_id)
        try:
            response = proxy(mine)
        except Exception:
            proxy.close()
            raise
        with self._lock:
            self._idle.append(proxy)
        return response.status, response

    def close(self):
        with self._lock:
            proxies, self._idle = self._idle, []
        for proxy in proxies:
            proxy.close()


class CancellablePlannerProxy(PlannerProxy):
    """A planner whose plans the router may cancel: the call's id travels as PlanPath.cancel_id, a cancel is
    that id on the planner's ~cancel topic."""

    def __init__(self, service: str, cancel_topic: str):
        super().__init__(service)
        self.cancel_topic = cancel_topic
        self._cancel = rospy.Publisher(cancel_topic, UInt64, queue_size=100)

    def cancel(self, call_id: int) -> None:
        self._cancel.publish(UInt64(call_id))


def planner_proxy(service: str, cancel_topic: str) -> PlannerProxy:
    """The proxy for a planner: cancellable when it has a ~cancel topic ("" for none)."""
    return CancellablePlannerProxy(service, cancel_topic) if cancel_topic else PlannerProxy(service)


class Every:
    """True at most once per `period_s` of `clock` (the first call is True); a period of 0: every call."""

    def __init__(self, period_s: float, clock=time.monotonic):
        self.period_s, self.clock = period_s, clock
        self._last = -math.inf

    def __call__(self) -> bool:
        now = self.clock()
        if now - self._last < self.period_s:
            return False
        self._last = now
        return True


def exit_fatal(error) -> None:
    """One FATAL line naming the cause, then exit status 1: never a node that runs half set up."""
    rospy.logfatal("%s", error)
    raise SystemExit(1) from None


def account(response):
    """(robot CPU-seconds, link bytes sent, received) the serving node reported for one call."""
    return response.cpu_s, response.bytes_sent, response.bytes_received


def recorder_connected(publisher, recorder: str) -> bool:
    """Whether the node `recorder` (a resolved name; "" for any node) has a connection to `publisher`.
    rospy keeps each subscriber's caller id on its connection (endpoint_id)."""
    impl = publisher.impl
    with impl.c_lock:
        subscribers = [getattr(connection, "endpoint_id", "") for connection in impl.connections]
    return bool(subscribers) if not recorder else recorder in subscribers


def wait_for_recorder(publishers, timeout_s: float, recorder: str) -> None:
    """Before serving, wait until the recorder (the node `recorder`, or with "" any subscriber) is connected
    to every publisher, so a recording starts with the first request. Another subscriber (a monitor, a
    test, `rostopic echo`) does not count: serving as soon as it connected lost the first records when
    rosbag connected later (found by the fault matrix)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not rospy.is_shutdown():
        if all(recorder_connected(publisher, recorder) for publisher in publishers):
            return
        time.sleep(0.05)
    if timeout_s > 0:
        rospy.logwarn("%s not connected to %s within %g s: serving anyway", recorder or "no subscriber",
                      publishers[0].resolved_name, timeout_s)


class StaleMapCheck:
    """Why a path was planned on a map older than the latest map_metadata announced, or None. The map in
    force is the one whose load time map_metadata carries (map_server and map_publisher stamp the grid at or
    after it). A load time of zero (a publisher that does not set it) or in the future (a clock gone wrong:
    no planner's map could ever match it) cannot tell an old map from the one in force: the check is off
    for that map, with one warning, rather than a wait on every request."""

    def __init__(self, map_info):
        self.map_info = map_info          # callable: the latest MapMetaData or None
        self._warned = set()

    def __call__(self, response):
        info = self.map_info()
        if info is None or response.map_stamp >= info.map_load_time:
            return None
        load_time = info.map_load_time
        if load_time.is_zero() or load_time > rospy.Time.now() + rospy.Duration(5.0):
            if load_time not in self._warned:
                self._warned.add(load_time)
                rospy.logwarn("map_metadata's load time %.3f is %s: paths cannot be checked against the map in "
                              "force", load_time.to_sec(), "zero" if load_time.is_zero() else "in the future")
            return None
        return (f"planned on the map of {response.map_stamp.to_sec():.3f}, the map in force was loaded at "
                f"{info.map_load_time.to_sec():.3f}")


def rejection(info, request):
    """The planners' verdict on a request refused for its input (no planner is called), or None."""
    if info is None:
        return None
    a, b, q = request.start, request.goal, info.origin.orientation
    return check_request(info.width, info.height, info.resolution, (info.origin.position.x, info.origin.position.y),
                         (q.x, q.y, q.z, q.w), a.header.frame_id, (a.pose.position.x, a.pose.position.y),
                         b.header.frame_id, (b.pose.position.x, b.pose.position.y), request.tolerance)


def stamped(msg):
    msg.header.stamp = rospy.Time.now()
    return msg


def decision_msg(routing, policy: str, model_steps: int) -> OffloadDecision:
    """The decision of one request; its state fields are the state schema's, named alike in the message."""
    state, decision = routing.state, routing.decision
    return stamped(OffloadDecision(
        request_id=routing.request_id, **state.as_dict(), action=decision.action, action_propensity=decision.propensity,
        q_local=decision.q_local, q_cloud=decision.q_cloud, policy=policy, model_steps=model_steps,
        probe=routing.probe, mode=routing.mode, routed=routing.action, breaker=routing.breaker,
        deadline_s=routing.deadline_s, model_version=decision.model_version))


def outcome_msg(outcome) -> OffloadOutcome:
    msg = stamped(OffloadOutcome(request_id=outcome.request_id, action=outcome.decision.action,
                                 delivered=outcome.delivered, delivered_s=outcome.delivered_s))
    if outcome.local is not None:
        msg.local_measured, msg.local_s, msg.local_status = True, outcome.local_s, outcome.local.status
    if outcome.cloud is not None:
        msg.cloud_measured, msg.cloud_s, msg.cloud_status = True, outcome.cloud_s, outcome.cloud.status
        msg.cloud_timeout = outcome.cloud_timeout
    # reward_valid marks a reward from two measured latencies (a transition-table row); an imputed one is
    # recorded too, with the side it imputed.
    msg.reward_valid = outcome.reward is not None and outcome.imputed is None
    msg.reward = outcome.reward if outcome.reward is not None else float("nan")
    msg.imputed = OffloadOutcome.NONE if outcome.imputed is None else outcome.imputed
    msg.transitions, msg.hedged = outcome.transitions, outcome.hedged
    msg.robot_cpu_s, msg.bridge_cpu_s = outcome.robot_cpu_s, outcome.bridge_cpu_s
    msg.learner_cpu_s = outcome.learner_cpu_s
    msg.link_bytes_sent, msg.link_bytes_received = outcome.bytes_sent, outcome.bytes_received
    msg.loss_valid = outcome.loss is not None
    msg.loss = outcome.loss if outcome.loss is not None else float("nan")
    return msg


def config_msg(router_config, learner, seed: int, alpha: float) -> LearnerConfig:
    config, dqn = router_config, getattr(learner.agent, "config", None)
    return stamped(LearnerConfig(
        policy=learner.config.policy, mode=config.mode, learn=learner.learns, explore=learner.config.explore,
        alpha=alpha, beta=1.0 - alpha, gamma=dqn.gamma if dqn else float("nan"),
        epsilon=dqn.epsilon if dqn else float("nan"), learning_starts=dqn.learning_starts if dqn else 0,
        probe_rate=1.0 if config.probes_every_request else config.probe_rate, cloud_timeout_s=config.cloud_timeout_s,
        hedge=config.hedge, hedge_deadline_s=config.hedge_deadline_s, hedge_quantile=config.hedge_quantile,
        hedge_min_s=config.hedge_min_s, hedge_max_s=config.hedge_max_s,
        breaker_failures=config.breaker.failures_to_open, breaker_max_round_trip_s=config.breaker.max_round_trip_s,
        breaker_retry_s=config.breaker.retry_after_s, seed=seed,
        dqn_config_json=json.dumps(asdict(dqn), default=list) if dqn else ""))


def stats_msg(learner) -> TrainingStats:
    stats = learner.stats()
    return stamped(TrainingStats(
        policy=learner.config.policy, learning=bool(learner.policy.learns), steps=stats["steps"],
        gradient_steps=stats["gradient_steps"], replay_size=stats["replay_size"], epsilon=stats["epsilon"],
        recent_window=stats["recent_window"], recent_loss=stats["recent_loss"],
        recent_accuracy=stats["recent_accuracy"], checkpoint_failures=stats["checkpoint_failures"]))


def path_of(side) -> Path:
    """A side's latched path for one request: its path (a probe's losing side too), or an empty one in the map
    frame (the side failed or did not run): never a stale one."""
    if side is not None and side.status == PlanPathResponse.OK and side.response is not None:
        return side.response.path
    empty = stamped(Path())
    empty.header.frame_id = "map"
    return empty


class RvizGoals:
    """RViz 2D Nav Goal: plan from the robot's pose (tf map -> base frame when tf2_ros has it, else
    /initialpose or ~start_x/~start_y, else the map centre) through `serve`, like any other request."""

    def __init__(self, serve, tolerance: float, start_xy, base_frame: str, map_info):
        self.serve, self.tolerance, self.start_xy, self.base_frame = serve, tolerance, start_xy, base_frame
        self.map_info = map_info        # callable: the latest MapMetaData or None
        self.tf_buffer = None
        try:
            import tf2_ros
            self.tf_buffer = tf2_ros.Buffer()
            tf2_ros.TransformListener(self.tf_buffer)
        except ImportError:
            rospy.loginfo("tf2_ros not installed: RViz goals start from ~start_x/~start_y or /initialpose")

    def on_initial_pose(self, msg):
        self.start_xy = (msg.pose.pose.position.x, msg.pose.pose.position.y)

    def robot_start(self, goal: PoseStamped) -> PoseStamped:
        start = PoseStamped()
        start.header.frame_id = goal.header.frame_id or "map"
        start.pose.orientation.w = 1.0
        if self.tf_buffer is not None:
            try:
                transform = self.tf_buffer.lookup_transform(start.header.frame_id, self.base_frame, rospy.Time(0),
                                                            rospy.Duration(0.2))
                start.pose.position.x = transform.transform.translation.x
                start.pose.position.y = transform.transform.translation.y
                return start
            except Exception as error:  # tf raises several lookup errors; any means "no pose"
                rospy.logdebug("no robot pose in tf: %s", error)
        x, y = self.start_xy
        if not (math.isfinite(x) and math.isfinite(y)):
            info = self.map_info()
            if info is None:
                raise ValueError("no start: no tf pose, no ~start_x/~start_y and no map yet")
            x = info.origin.position.x + 0.5 * info.width * info.resolution
            y = info.origin.position.y + 0.5 * info.height * info.resolution
        start.pose.position.x, start.pose.position.y = x, y
        return start

    def on_goal(self, goal: PoseStamped):
        try:
            start = self.robot_start(goal)
        except ValueError as error:
            rospy.logwarn("goal ignored: %s", error)
            return
        response = self.serve(PlanPathRequest(start=start, goal=goal, tolerance=self.tolerance))
        if response.status != PlanPathResponse.OK:
            rospy.logwarn("no path to the RViz goal (status %d): %s", response.status, response.message)
