"""offload_learner: the offloading router node. It serves the same PlanPath and GetPlan services as the
two planners it routes to (the local planner node and the cloud bridge), decides per request with
offload_learner_py.online.router, and publishes every decision, outcome and training statistic so a bag
rebuilds the transition table. Thin: all logic lives in the ROS-free router."""
import json
import math
import time
from dataclasses import asdict

import rospy
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import MapMetaData, Path
from nav_msgs.srv import GetPlan, GetPlanResponse
from offload_msgs.msg import LearnerConfig, LinkLatency, OffloadDecision, OffloadOutcome, RequestRejected, \
    TrainingStats
from offload_msgs.srv import PlanPath, PlanPathRequest, PlanPathResponse

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.online.breaker import BreakerConfig
from offload_learner_py.core.checkpoint import IncompatibleCheckpointError
from offload_learner_py.online.cpu import make_cpu_sampler
from offload_learner_py.online.request_check import check_request
from offload_learner_py.core.reward import CostWeights
from offload_learner_py.online.session import LearnerSession, SessionConfig
from offload_learner_py.online.router import OffloadRouter, RouterConfig, Statuses
from offload_learner_py.core.state import State, input_size



class RosLog:
    """The session's logger, on rosout."""
    debug, info, warning, error = (staticmethod(rospy.logdebug), staticmethod(rospy.loginfo),
                                   staticmethod(rospy.logwarn), staticmethod(rospy.logerr))


class PlannerProxy:
    """A persistent connection to one planner's ~plan, reopened after any failure. Each side is
    called by one thread at a time (the router serialises requests), so one connection suffices."""

    def __init__(self, service: str):
        self.service = service
        self._proxy = None

    def __call__(self, request):
        if self._proxy is None:
            self._proxy = rospy.ServiceProxy(self.service, PlanPath, persistent=True)
        try:
            response = self._proxy(request)
        except Exception:
            self.close()
            raise
        return response.status, response

    def close(self):
        if self._proxy is not None:
            self._proxy.close()
            self._proxy = None


def recorder_connected(publisher, recorder: str) -> bool:
    """Whether the node `recorder` (a resolved name; "" for any node) has a connection to `publisher`.
    rospy keeps each subscriber's caller id on its connection (endpoint_id)."""
    impl = publisher.impl
    with impl.c_lock:
        subscribers = [getattr(connection, "endpoint_id", "") for connection in impl.connections]
    return bool(subscribers) if not recorder else recorder in subscribers


class LearnerNode:
    def __init__(self):
        p = lambda name, default: rospy.get_param("~" + name, default)  # noqa: E731
        seed = int(p("seed", 1))
        self.session = LearnerSession(SessionConfig(
            policy=str(p("policy", "dqn")), checkpoint=str(p("checkpoint", "")), model=str(p("model", "")),
            checkpoint_every=int(p("checkpoint_every", 50)), learn=bool(p("learn", True)),
            # Learning mode runs both sides anyway and deployed mode explores with its probes:
            # epsilon-greedy exploration would only cost the robot time, so it is off unless asked for.
            explore=bool(p("explore", False)), seed=seed, dqn=p("dqn", {}) or {},
            threshold_input_size=float(p("threshold_input_size", 1.1)), stats_window=int(p("stats_window", 50)),
            progress_every=int(p("progress_every", 25))), RosLog)
        self.policy = self.session.policy
        alpha = float(p("alpha", 0.5))
        breaker = BreakerConfig(failures_to_open=int(p("breaker_failures", 3)),
                                max_round_trip_s=float(p("breaker_max_round_trip_s", 1.0)),
                                retry_after_s=float(p("breaker_retry_s", 5.0)))
        self.router_config = RouterConfig(mode=str(p("mode", "deployed")), probe_rate=float(p("probe_rate", 0.05)),
                                          cloud_timeout_s=float(p("cloud_timeout_s", 5.0)),
                                          weights=CostWeights(alpha, 1.0 - alpha), seed=seed,
                                          map_wait_s=float(p("map_wait_s", 2.0)), hedge=bool(p("hedge", False)),
                                          hedge_deadline_s=float(p("hedge_deadline_s", 0.0)),
                                          hedge_quantile=float(p("hedge_quantile", 0.95)),
                                          hedge_min_s=float(p("hedge_min_s", 0.05)),
                                          hedge_max_s=float(p("hedge_max_s", 1.0)), breaker=breaker)
        self.cpu = make_cpu_sampler(str(p("cpu_cores", "")), str(p("cpu_cgroup", "")))
        # With a cgroup budget (nanosecond counters) u_t covers the time since the last request ended,
        # so it sees the load the next plan will meet, not the previous plan. Jiffy counters (10 ms)
        # are too coarse for that and keep the window from request to request.
        self.cpu_window_from_outcome = bool(p("cpu_cgroup", ""))
        self.goal_tolerance = float(p("goal_tolerance", 0.5))
        self.start_xy = (float(p("start_x", float("nan"))), float(p("start_y", float("nan"))))
        self.base_frame = str(p("base_frame", "base_link"))
        self.map_info = None
        self.map_frame = "map"
        self.round_trip_s = None
        self.tf_buffer = self._tf_buffer()

        local = PlannerProxy(str(p("local_service", "/planner/plan")))
        cloud = PlannerProxy(str(p("cloud_service", "/cloud_bridge/plan")))
        self.sides = (local, cloud)
        wait_s = float(p("service_wait_s", 60.0))
        for side in self.sides:
            rospy.loginfo("waiting for %s", side.service)
            rospy.wait_for_service(side.service, timeout=wait_s)
        statuses = Statuses(ok=PlanPathResponse.OK, cloud_timeout=PlanPathResponse.CLOUD_TIMEOUT,
                            cloud_error=PlanPathResponse.CLOUD_ERROR, stale_map=PlanPathResponse.STALE_MAP)
        self._stamp_warned = set()
        self.decision_pub = rospy.Publisher("~decision", OffloadDecision, queue_size=100)
        self.outcome_pub = rospy.Publisher("~outcome", OffloadOutcome, queue_size=100)
        self.stats_pub = rospy.Publisher("~stats", TrainingStats, queue_size=10)
        self.path_pubs = {LOCAL: rospy.Publisher("~path_local", Path, queue_size=1, latch=True),
                          CLOUD: rospy.Publisher("~path_cloud", Path, queue_size=1, latch=True)}
        self.goal_pub = rospy.Publisher("~goal", PoseStamped, queue_size=10, latch=True)
        self.config_pub = rospy.Publisher("~config", LearnerConfig, queue_size=1, latch=True)
        self.rejected_pub = rospy.Publisher("~rejected", RequestRejected, queue_size=100)
        self.publish_config(seed, alpha)
        recorder = str(p("recorder_node", "offload_record"))
        self._wait_for_recorder(float(p("wait_for_recorder_s", 0.0)),
                                rospy.names.resolve_name(recorder) if recorder else "")
        self.router = OffloadRouter(self.policy, local, cloud, statuses, self.router_config,
                                    on_decision=self.publish_decision, on_outcome=self.on_outcome,
                                    stale=self.stale_map, account=self.account)
        rospy.Subscriber("map_metadata", MapMetaData, self.on_map_metadata, queue_size=1)
        latency_topic = str(p("latency_topic", "/cloud_bridge/latency"))
        rospy.Subscriber(latency_topic, LinkLatency, self.on_latency, queue_size=10)
        # s_t needs the map's size and a first round trip: serve once both are in (or the wait is over).
        deadline = time.monotonic() + wait_s
        while (self.map_info is None or self.round_trip_s is None) and time.monotonic() < deadline \
                and not rospy.is_shutdown():
            time.sleep(0.05)
        if self.map_info is None or self.round_trip_s is None:
            rospy.logwarn("no %s yet: requests are planned locally and not learned until it arrives",
                          "map_metadata" if self.map_info is None else latency_topic)
        rospy.Subscriber("/move_base_simple/goal", PoseStamped, self.on_goal, queue_size=10)
        rospy.Subscriber("/initialpose", PoseWithCovarianceStamped, self.on_initial_pose, queue_size=1)
        self.plan_srv = rospy.Service("~plan", PlanPath, self.on_plan)
        self.make_plan_srv = rospy.Service("~make_plan", GetPlan, self.on_make_plan)
        # Request ids continue across restarts (a bag may hold several sessions): microseconds since
        # the epoch at start, then one per request.
        self.router.next_request_id = time.time_ns() // 1000
        rospy.on_shutdown(self.shutdown)
        rospy.loginfo("offload learner ready: %s mode, policy %s, learn %s, probe rate %.2f, hedge %s, routing "
                      "between %s and %s", self.router_config.mode, self.session.config.policy, self.session.learns,
                      1.0 if self.router_config.probes_every_request else self.router_config.probe_rate,
                      self.router_config.hedge, local.service, cloud.service)

    def _wait_for_recorder(self, timeout_s: float, recorder: str) -> None:
        """Before serving, wait until the recorder (the node `recorder`, or with "" any subscriber) is
        connected to ~decision and ~outcome, so a recording starts with the first request. Another
        subscriber (a monitor, a test, `rostopic echo`) does not count: serving as soon as it connected lost
        the first records when rosbag connected later (found by the fault matrix)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and not rospy.is_shutdown():
            if all(recorder_connected(publisher, recorder) for publisher in (self.decision_pub, self.outcome_pub)):
                return
            time.sleep(0.05)
        if timeout_s > 0:
            rospy.logwarn("%s not connected to %s within %g s: serving anyway", recorder or "no subscriber",
                          self.decision_pub.resolved_name, timeout_s)

    @staticmethod
    def _tf_buffer():
        try:
            import tf2_ros
        except ImportError:
            rospy.loginfo("tf2_ros not installed: RViz goals start from ~start_x/~start_y or /initialpose")
            return None
        buffer = tf2_ros.Buffer()
        tf2_ros.TransformListener(buffer)
        return buffer

    # --- inputs ---------------------------------------------------------------------------------
    def on_map_metadata(self, msg):
        self.map_info = msg

    def stale_map(self, response):
        """Why a path was planned on a map older than the latest map_metadata announced, or None. The
        map in force is the one whose load time map_metadata carries (map_server and map_publisher stamp
        the grid at or after it). A load time of zero (a publisher that does not set it) or in the future (a
        clock gone wrong: no planner's map could ever match it) cannot tell an old map from the one in force:
        the check is off for that map, with one warning, rather than a wait on every request."""
        info = self.map_info
        if info is None or response.map_stamp >= info.map_load_time:
            return None
        load_time = info.map_load_time
        if load_time.is_zero() or load_time > rospy.Time.now() + rospy.Duration(5.0):
            if load_time not in self._stamp_warned:
                self._stamp_warned.add(load_time)
                rospy.logwarn("map_metadata's load time %.3f is %s: paths cannot be checked against the map in "
                              "force", load_time.to_sec(), "zero" if load_time.is_zero() else "in the future")
            return None
        return (f"planned on the map of {response.map_stamp.to_sec():.3f}, the map in force was loaded at "
                f"{info.map_load_time.to_sec():.3f}")

    def on_latency(self, msg):
        self.round_trip_s = msg.round_trip_s
        if msg.source == LinkLatency.HEARTBEAT:
            self.router.breaker.record_heartbeat(msg.reachable, msg.round_trip_s)

    @staticmethod
    def account(response):
        """(robot CPU-seconds, link bytes sent, received) the serving node reported for one call."""
        return response.cpu_s, response.bytes_sent, response.bytes_received

    def on_initial_pose(self, msg):
        self.start_xy = (msg.pose.pose.position.x, msg.pose.pose.position.y)

    def robot_start(self, goal: PoseStamped) -> PoseStamped:
        start = PoseStamped()
        start.header.frame_id = goal.header.frame_id or self.map_frame
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
            info = self.map_info
            if info is None:
                raise ValueError("no start: no tf pose, no ~start_x/~start_y and no map yet")
            x = info.origin.position.x + 0.5 * info.width * info.resolution
            y = info.origin.position.y + 0.5 * info.height * info.resolution
        start.pose.position.x, start.pose.position.y = x, y
        return start

    def on_goal(self, goal: PoseStamped):
        """RViz 2D Nav Goal: plan from the robot's pose through the router, like any other request."""
        try:
            start = self.robot_start(goal)
        except ValueError as error:
            rospy.logwarn("goal ignored: %s", error)
            return
        response = self.serve(PlanPathRequest(start=start, goal=goal, tolerance=self.goal_tolerance))
        if response.status != PlanPathResponse.OK:
            rospy.logwarn("no path to the RViz goal (status %d): %s", response.status, response.message)

    def build_state(self, request):
        """s_t, or None when it cannot be built (no map metadata yet, a pose that is not finite): such a
        request still goes to the local planner, which names the problem, and teaches nothing."""
        info = self.map_info
        if info is None or self.round_trip_s is None:
            return None
        a, b = request.start.pose.position, request.goal.pose.position
        try:
            d = input_size((a.x, a.y), (b.x, b.y), info.resolution, info.width * info.height)
            return State(d, self.cpu.sample(), self.round_trip_s)
        except (ValueError, RuntimeError, OSError) as error:
            rospy.logwarn("request not learnable: %s", error)
            return None

    # --- serving --------------------------------------------------------------------------------
    def rejection(self, request):
        """The planners' verdict on a request refused for its input (no planner is called), or None."""
        info = self.map_info
        if info is None:
            return None
        a, b, q = request.start, request.goal, info.origin.orientation
        return check_request(info.width, info.height, info.resolution, (info.origin.position.x, info.origin.position.y),
                             (q.x, q.y, q.z, q.w), a.header.frame_id, (a.pose.position.x, a.pose.position.y),
                             b.header.frame_id, (b.pose.position.x, b.pose.position.y), request.tolerance)

    def serve(self, request) -> PlanPathResponse:
        arrived = time.perf_counter()    # the router's clock: the caller's latency starts here
        refused = self.rejection(request)
        if refused is not None:
            msg = RequestRejected(status=refused.status, message=refused.message)
            msg.header.stamp = rospy.Time.now()
            self.rejected_pub.publish(msg)
            rospy.logwarn_throttle(10.0, "request refused (status %d): %s", refused.status, refused.message)
            return PlanPathResponse(status=refused.status, message=refused.message)
        self.goal_pub.publish(request.goal)
        result = self.router.route(request, self.build_state(request), arrived)
        if result.response is None:
            return PlanPathResponse(status=result.status, message=result.raised)
        if result.note:   # a path on the last map the planner took, never as OK: STALE_MAP and why
            rospy.logwarn_throttle(10.0, "returned a path %s", result.note)
            result.response.status, result.response.message = result.status, result.note
        return result.response

    def on_plan(self, request):
        return self.serve(request)

    def on_make_plan(self, request):
        response = self.serve(PlanPathRequest(start=request.start, goal=request.goal, tolerance=request.tolerance))
        return GetPlanResponse(plan=response.path if response.status == PlanPathResponse.OK else Path())

    # --- records --------------------------------------------------------------------------------
    def publish_decision(self, routing):
        request_id, state, decision, probe = routing.request_id, routing.state, routing.decision, routing.probe
        msg = OffloadDecision(request_id=request_id, input_size=state.input_size,
                              cpu_availability=state.cpu_availability, round_trip_s=state.round_trip_s,
                              action=decision.action, action_propensity=decision.propensity,
                              q_local=decision.q_local, q_cloud=decision.q_cloud, policy=self.session.config.policy,
                              model_steps=self.policy.steps, probe=probe, mode=routing.mode, routed=routing.action,
                              breaker=routing.breaker, deadline_s=routing.deadline_s)
        msg.header.stamp = rospy.Time.now()
        self.decision_pub.publish(msg)

    def on_outcome(self, outcome):
        if self.cpu_window_from_outcome:
            try:
                self.cpu.sample()
            except (OSError, RuntimeError) as error:
                rospy.logwarn_throttle(10, "cannot read the robot's CPU budget: %s", error)
        if outcome.state is None:
            return   # not a decision: nothing to pair it with (the planner's status told the caller why)
        msg = OffloadOutcome(request_id=outcome.request_id, action=outcome.decision.action,
                             delivered=outcome.delivered, delivered_s=outcome.delivered_s)
        msg.header.stamp = rospy.Time.now()
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
        msg.transitions = outcome.transitions
        msg.hedged = outcome.hedged
        msg.robot_cpu_s, msg.bridge_cpu_s = outcome.robot_cpu_s, outcome.bridge_cpu_s
        msg.link_bytes_sent, msg.link_bytes_received = outcome.bytes_sent, outcome.bytes_received
        msg.loss_valid = outcome.loss is not None
        msg.loss = outcome.loss if outcome.loss is not None else float("nan")
        self.outcome_pub.publish(msg)
        # Each side's latched path is this request's (a probe's losing side too), or empty: never a stale one.
        for action, side in ((LOCAL, outcome.local), (CLOUD, outcome.cloud)):
            planned = side is not None and side.status == PlanPathResponse.OK and side.response is not None
            empty = Path()
            empty.header.frame_id = self.map_frame
            empty.header.stamp = rospy.Time.now()
            self.path_pubs[action].publish(side.response.path if planned else empty)
        progress = self.session.record(outcome)
        self.publish_stats()
        if progress:
            rospy.loginfo("%s", progress)

    def publish_config(self, seed: int, alpha: float):
        config, session = self.router_config, self.session.config
        dqn = getattr(self.session.agent, "config", None)
        msg = LearnerConfig(policy=session.policy, mode=config.mode, learn=self.session.learns,
                            explore=session.explore, alpha=alpha, beta=1.0 - alpha,
                            gamma=dqn.gamma if dqn else float("nan"), epsilon=dqn.epsilon if dqn else float("nan"),
                            learning_starts=dqn.learning_starts if dqn else 0,
                            probe_rate=1.0 if config.probes_every_request else config.probe_rate,
                            cloud_timeout_s=config.cloud_timeout_s, hedge=config.hedge,
                            hedge_deadline_s=config.hedge_deadline_s, hedge_quantile=config.hedge_quantile,
                            hedge_min_s=config.hedge_min_s, hedge_max_s=config.hedge_max_s,
                            breaker_failures=config.breaker.failures_to_open,
                            breaker_max_round_trip_s=config.breaker.max_round_trip_s,
                            breaker_retry_s=config.breaker.retry_after_s, seed=seed,
                            dqn_config_json=json.dumps(asdict(dqn), default=list) if dqn else "")
        msg.header.stamp = rospy.Time.now()
        self.config_pub.publish(msg)

    def publish_stats(self):
        stats = self.session.stats()
        msg = TrainingStats(policy=self.session.config.policy, learning=bool(self.policy.learns),
                            steps=stats["steps"], gradient_steps=stats["gradient_steps"],
                            replay_size=stats["replay_size"], epsilon=stats["epsilon"],
                            recent_window=stats["recent_window"], recent_loss=stats["recent_loss"],
                            recent_accuracy=stats["recent_accuracy"], checkpoint_failures=stats["checkpoint_failures"])
        msg.header.stamp = rospy.Time.now()
        self.stats_pub.publish(msg)

    def shutdown(self):
        if not self.router.wait_idle(10.0):
            rospy.logwarn("the last request did not finish within 10 s")
        self.session.close()
        for side in self.sides:
            side.close()


def main():
    """Offloading learner node.

    Parameters (private):
      ~policy (str, "dqn")               dqn, local, cloud, random or threshold
      ~model (str, "")                   checkpoint to start from (when ~checkpoint does not exist yet)
      ~checkpoint (str, "")              checkpoint written every ~checkpoint_every learned steps and on
                                         shutdown; loaded at start when it exists (resume)
      ~checkpoint_every (int, 50)
      ~learn (bool, true)                false freezes the model (greedy, no training)
      ~mode (str, deployed)              learning: every request a probe (both sides, both actions learned);
                                         deployed: the chosen side alone, ~probe_rate of requests probed
      ~probe_rate (float, 0.05)          deployed: share of requests planned on both sides
      ~explore (bool, false)             epsilon-greedy actions (DQNConfig epsilon); off: greedy
      ~hedge (bool, false)               start the other side when the chosen one misses its deadline
      ~hedge_deadline_s (float, 0)       fixed deadline; 0: ~hedge_quantile of the side's latency model,
      ~hedge_quantile (float, 0.95)      clamped to [~hedge_min_s (0.05), ~hedge_max_s (1.0)]
      ~breaker_failures (int, 3)         cloud failures in a row that stop offloading (0: no breaker)
      ~breaker_max_round_trip_s (float, 1.0)  a heartbeat round trip above this stops offloading too
      ~breaker_retry_s (float, 5.0)      while stopped, one request this often is a probe that tests the link
      ~cloud_timeout_s (float, 5.0)      l_cloud of a cloud timeout or error
      ~alpha (float, 0.5)                weight of local time in the cost (beta = 1 - alpha)
      ~seed (int, 1)                     exploration and probe draws, network initialisation
      ~dqn (dict, {})                    DQNConfig overrides (learning_starts, epsilon, ...)
      ~threshold_input_size (float, 1.1) d_t above which the threshold policy offloads
      ~local_service (str, /planner/plan), ~cloud_service (str, /cloud_bridge/plan)
      ~latency_topic (str, /cloud_bridge/latency)   b_t source (offload_msgs/LinkLatency)
      ~cpu_cgroup (str, "")              cgroup v1 of the robot's processes: u_t = unused share of its quota
      ~cpu_cores (str, "")               else u_t = idle share of these cores ("0", "0-1"); else of the host
      ~goal_tolerance (float, 0.5)       tolerance of RViz goals (m)
      ~start_x, ~start_y (float)         start of RViz goals when tf has no robot pose (default map centre)
      ~base_frame (str, base_link)
      ~map_wait_s (float, 2.0)           how long a planner still on an older map than map_metadata's is
                                         asked again before its answer counts as failed (never delivered)
      ~service_wait_s (float, 60)        how long to wait for both planners at start
      ~wait_for_recorder_s (float, 0)    wait this long for ~recorder_node to subscribe to ~decision and ~outcome
      ~recorder_node (str, offload_record)  the recorder's node name (record.launch's); "" for any subscriber
      ~progress_every (int, 25), ~stats_window (int, 50)
    """
    rospy.init_node("offload_learner")
    try:
        node = LearnerNode()
    except (ValueError, OSError, IncompatibleCheckpointError, rospy.ROSException) as error:
        rospy.logfatal("%s", error)
        raise SystemExit(1) from None
    rospy.spin()
    return node


if __name__ == "__main__":
    main()
