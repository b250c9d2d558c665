"""offload_learner: the offloading router node. It serves the same PlanPath and GetPlan services as the
two planners it routes to (the local planner node and the cloud bridge), and wires the ROS-free online loop
(offload_learner_py.online: the router acts, the learner learns) to ROS: it builds s_t from the messages and
publishes every decision, outcome and training statistic, so a bag rebuilds the transition table. Its
topics, services and parameters are in the package README; their defaults in launch/config/learner.yaml."""
import time

import rospy
import torch
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import MapMetaData, Path
from nav_msgs.srv import GetPlan, GetPlanResponse
from offload_msgs.msg import LearnerConfig, LinkLatency, OffloadDecision, OffloadOutcome, RequestRejected, \
    TrainingStats
from offload_msgs.srv import PlanPath, PlanPathRequest, PlanPathResponse

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.checkpoint import IncompatibleCheckpointError
from offload_learner_py.core.reward import CostWeights
from offload_learner_py.core.state import State, input_size
from offload_learner_py.nodes.learner_io import STATUSES, PlannerProxy, RosLog, planner_proxy, RvizGoals, \
    StaleMapCheck, account, config_msg, decision_msg, exit_fatal, outcome_msg, path_of, rejection, stamped, stats_msg, \
    wait_for_recorder
from offload_learner_py.online.breaker import BreakerConfig
from offload_learner_py.online.cpu import make_cpu_sampler
from offload_learner_py.online.learning import OnlineLearner
from offload_learner_py.online.router import OffloadRouter
from offload_learner_py.online.router_types import RouterConfig
from offload_learner_py.online.session import SessionConfig, dqn_settings
from offload_cloud.gc_pauses import freeze_startup_heap


class LearnerNode:
    def __init__(self):
        p = lambda name, default: rospy.get_param("~" + name, default)  # noqa: E731
        seed, alpha = int(p("seed", 1)), float(p("alpha", 0.5))
        # One thread: fastest for this small network, leaves the robot's other cores to the planner, and keeps the
        # learner's CPU per request (its thread's time) whole.
        torch.set_num_threads(int(p("torch_threads", 1)))
        dqn = dqn_settings(str(p("mode", "deployed")), p("dqn", {}), p("deployed_dqn", {}))
        session = SessionConfig(
            policy=str(p("policy", "dqn")), checkpoint=str(p("checkpoint", "")), model=str(p("model", "")),
            checkpoint_every=int(p("checkpoint_every", 50)), learn=bool(p("learn", True)),
            # Learning mode runs both sides anyway and deployed mode explores with its probes:
            # epsilon-greedy exploration would only cost the robot time, so it is off unless asked for.
            explore=bool(p("explore", False)), seed=seed, dqn=dqn,
            threshold_input_size=float(p("threshold_input_size", 1.1)), stats_window=int(p("stats_window", 50)),
            progress_every=int(p("progress_every", 25)))
        breaker = BreakerConfig(failures_to_open=int(p("breaker_failures", 3)),
                                max_round_trip_s=float(p("breaker_max_round_trip_s", 1.0)),
                                retry_after_s=float(p("breaker_retry_s", 5.0)))
        config = self.router_config = RouterConfig(
            mode=str(p("mode", "deployed")), probe_rate=float(p("probe_rate", 0.05)),
            cloud_timeout_s=float(p("cloud_timeout_s", 5.0)), weights=CostWeights(alpha, 1.0 - alpha), seed=seed,
            map_wait_s=float(p("map_wait_s", 2.0)), hedge=bool(p("hedge", False)),
            hedge_deadline_s=float(p("hedge_deadline_s", 0.0)), hedge_quantile=float(p("hedge_quantile", 0.95)),
            hedge_min_s=float(p("hedge_min_s", 0.05)), hedge_max_s=float(p("hedge_max_s", 1.0)), breaker=breaker)
        self.learner = OnlineLearner.resume(session, STATUSES, RosLog, weights=config.weights,
                                            cloud_timeout_s=config.cloud_timeout_s, latency_model=config.latency_model)
        self.cpu = make_cpu_sampler(str(p("cpu_cores", "")), str(p("cpu_cgroup", "")))
        # With a cgroup budget (nanosecond counters) u_t covers the time since the last request ended,
        # so it sees the load the next plan will meet, not the previous plan. Jiffy counters (10 ms)
        # are too coarse for that and keep the window from request to request.
        self.cpu_window_from_outcome = bool(p("cpu_cgroup", ""))
        self.map_info, self.round_trip_s = None, None
        self.goals = RvizGoals(self.serve, float(p("goal_tolerance", 0.5)),
                               (float(p("start_x", float("nan"))), float(p("start_y", float("nan")))),
                               str(p("base_frame", "base_link")), lambda: self.map_info)
        # The local planner's plans are cancelled through its ~cancel topic when a newer request needs it; the
        # cloud side runs calls concurrently and is never cancelled.
        self.sides = (planner_proxy(str(p("local_service", "/planner/plan")), str(p("local_cancel_topic", "/planner/cancel"))),
                      PlannerProxy(str(p("cloud_service", "/cloud_bridge/plan"))))
        wait_s = float(p("service_wait_s", 60.0))
        for side in self.sides:
            rospy.loginfo("waiting for %s", side.service)
            rospy.wait_for_service(side.service, timeout=wait_s)
        self.decision_pub = rospy.Publisher("~decision", OffloadDecision, queue_size=100)
        self.outcome_pub = rospy.Publisher("~outcome", OffloadOutcome, queue_size=100)
        self.stats_pub = rospy.Publisher("~stats", TrainingStats, queue_size=10)
        self.path_pubs = {LOCAL: rospy.Publisher("~path_local", Path, queue_size=1, latch=True),
                          CLOUD: rospy.Publisher("~path_cloud", Path, queue_size=1, latch=True)}
        self.goal_pub = rospy.Publisher("~goal", PoseStamped, queue_size=10, latch=True)
        self.config_pub = rospy.Publisher("~config", LearnerConfig, queue_size=1, latch=True)
        self.rejected_pub = rospy.Publisher("~rejected", RequestRejected, queue_size=100)
        self.config_pub.publish(config_msg(config, self.learner, seed, alpha))
        recorder = str(p("recorder_node", "offload_record"))
        wait_for_recorder((self.decision_pub, self.outcome_pub), float(p("wait_for_recorder_s", 0.0)),
                          rospy.names.resolve_name(recorder) if recorder else "")
        self.router = OffloadRouter(self.learner, *self.sides, STATUSES, config,
                                    on_decision=self.publish_decision, on_outcome=self.on_outcome,
                                    stale=StaleMapCheck(lambda: self.map_info), account=account)
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
        rospy.Subscriber("/move_base_simple/goal", PoseStamped, self.goals.on_goal, queue_size=10)
        rospy.Subscriber("/initialpose", PoseWithCovarianceStamped, self.goals.on_initial_pose, queue_size=1)
        self.plan_srv = rospy.Service("~plan", PlanPath, self.serve)
        self.make_plan_srv = rospy.Service("~make_plan", GetPlan, self.on_make_plan)
        # Request ids continue across restarts (a bag may hold several sessions): microseconds since
        # the epoch at start, then one per request.
        self.router.next_request_id = time.time_ns() // 1000
        rospy.on_shutdown(self.shutdown)
        rospy.loginfo("offload learner ready: %s mode, policy %s, learn %s, probe rate %.2f, hedge %s, routing "
                      "between %s and %s", config.mode, session.policy, self.learner.learns,
                      1.0 if config.probes_every_request else config.probe_rate, config.hedge,
                      *(side.service for side in self.sides))

    def on_map_metadata(self, msg):
        self.map_info = msg

    def on_latency(self, msg):
        self.round_trip_s = msg.round_trip_s
        if msg.source == LinkLatency.HEARTBEAT:
            self.router.breaker.record_heartbeat(msg.reachable, msg.round_trip_s)

    def build_state(self, request):
        """s_t, or None when it cannot be built (no map metadata yet, a pose that is not finite): such a
        request still goes to the local planner, which names the problem, and teaches nothing."""
        info = self.map_info
        if info is None or self.round_trip_s is None:
            return None
        a, b = request.start.pose.position, request.goal.pose.position
        try:
            d = input_size((a.x, a.y), (b.x, b.y), info.resolution, info.width * info.height)
            return State(input_size=d, cpu_availability=self.cpu.sample(), round_trip_s=self.round_trip_s)
        except (ValueError, RuntimeError, OSError) as error:
            rospy.logwarn("request not learnable: %s", error)
            return None

    def serve(self, request) -> PlanPathResponse:
        arrived = time.perf_counter()    # the router's clock: the caller's latency starts here
        refused = rejection(self.map_info, request)   # refused for its input: answered, never a decision
        if refused is not None:
            self.rejected_pub.publish(stamped(RequestRejected(status=refused.status, message=refused.message)))
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

    def on_make_plan(self, request):
        response = self.serve(PlanPathRequest(start=request.start, goal=request.goal, tolerance=request.tolerance))
        return GetPlanResponse(plan=response.path if response.status == PlanPathResponse.OK else Path())

    def publish_decision(self, routing):
        self.decision_pub.publish(decision_msg(routing, self.learner.config.policy, self.learner.policy.steps))

    def on_outcome(self, outcome):
        if self.cpu_window_from_outcome:
            try:
                self.cpu.sample()
            except (OSError, RuntimeError) as error:
                rospy.logwarn_throttle(10, "cannot read the robot's CPU budget: %s", error)
        if outcome.state is None:
            return   # not a decision: nothing to pair it with (the planner's status told the caller why)
        self.outcome_pub.publish(outcome_msg(outcome))
        # Each side's latched path is this request's (a probe's losing side too), or empty: never a stale one.
        for action, side in ((LOCAL, outcome.local), (CLOUD, outcome.cloud)):
            self.path_pubs[action].publish(path_of(side))
        self.stats_pub.publish(stats_msg(self.learner))   # the learner counted it and saved when due

    def shutdown(self):
        if not self.router.wait_idle(10.0):
            rospy.logwarn("the last request did not finish within 10 s")
        self.learner.close()
        for side in self.sides:
            side.close()


def main():
    """Runs the node; a setting, key or checkpoint it cannot use is one FATAL line and exit status 1."""
    rospy.init_node("offload_learner")
    try:
        LearnerNode()
    except (ValueError, OSError, IncompatibleCheckpointError, rospy.ROSException) as error:
        exit_fatal(error)
    freeze_startup_heap()
    rospy.spin()


if __name__ == "__main__":
    main()
