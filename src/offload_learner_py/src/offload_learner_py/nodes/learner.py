"""offload_learner: the offloading router node. It serves the same PlanPath and GetPlan services as the
two planners it routes to (the local planner node and the cloud bridge), and wires the ROS-free online loop
(offload_learner_py.online: the router acts, the learner learns) to ROS: it builds s_t from the messages and
publishes every decision, outcome and training statistic, so a bag rebuilds the transition table. Its
topics, services and parameters are in the package README; their defaults are the config dataclasses' fields
(nodes/learner_params.py), launch/config/learner.yaml what a deployment overrides."""
import time

import rospy
import torch
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import MapMetaData, Path
from nav_msgs.srv import GetPlan, GetPlanResponse
from offload_msgs.msg import LinkLatency
from offload_msgs.srv import PlanPath, PlanPathRequest, PlanPathResponse

from offload_learner_py.core.checkpoint import IncompatibleCheckpointError
from offload_learner_py.core.state import STATE_SCHEMA, State, input_size
from offload_learner_py.nodes.learner_io import STATUSES, PlannerProxy, RosLog, planner_proxy, RvizGoals, \
    StaleMapCheck, account, exit_fatal, rejection, wait_for_recorder
from offload_learner_py.nodes.learner_fleet import NodeFleet
from offload_learner_py.nodes.learner_outputs import LearnerOutputs
from offload_learner_py.nodes.learner_params import read_learner_parameters
from offload_learner_py.nodes.learner_reconfigure import LearnerReconfigure
from offload_learner_py.online.breaker import LinkBreaker
from offload_learner_py.online.cpu import make_cpu_sampler
from offload_learner_py.online.plan_rate import PlanRateEstimator
from offload_learner_py.online.router import OffloadRouter
from offload_cloud.gc_pauses import freeze_startup_heap


class LearnerNode:
    def __init__(self):
        settings = read_learner_parameters(lambda name, default: rospy.get_param("~" + name, default))
        node, session, config = settings.node, settings.session, settings.router
        # One thread: fastest for this small network, leaves the robot's other cores to the planner, and keeps the
        # learner's CPU per request (its thread's time) whole.
        torch.set_num_threads(node.torch_threads)
        # With ~fleet_endpoint (deployed DQN) the robot decides with the fleet learner's versions and never trains.
        self.fleet = NodeFleet(settings.fleet, settings.guard, config.mode, session.policy, session.model, RosLog)
        self.learner = self.fleet.learner(session, RosLog, statuses=STATUSES, weights=config.weights,
                                          cloud_timeout_s=config.cloud_timeout_s, latency_model=config.latency_model)
        self.cpu = make_cpu_sampler(node.cpu_cores, node.cpu_cgroup)
        # With a cgroup budget (nanosecond counters) u_t covers the time since the last request ended,
        # so it sees the load the next plan will meet, not the previous plan. Jiffy counters (10 ms)
        # are too coarse for that and keep the window from request to request.
        self.cpu_window_from_outcome = bool(node.cpu_cgroup)
        # p_t: "not measured" (the value of records from before it) until the local planner has timed a plan.
        self.plan_rate = PlanRateEstimator(STATE_SCHEMA["local_plan_rate"].missing, node.plan_rate_weight)
        self.map_info, self.round_trip_s = None, None
        self.goals = RvizGoals(self.serve, node.goal_tolerance, (node.start_x, node.start_y), node.base_frame,
                               lambda: self.map_info)
        # The local planner's plans are cancelled through its ~cancel topic when a newer request needs it; the
        # cloud side runs calls concurrently and is never cancelled.
        self.sides = (planner_proxy(node.local_service, node.local_cancel_topic), PlannerProxy(node.cloud_service))
        wait_s = node.service_wait_s
        for side in self.sides:
            rospy.loginfo("waiting for %s", side.service)
            rospy.wait_for_service(side.service, timeout=wait_s)
        breaker = LinkBreaker(config.breaker)
        self.outputs = LearnerOutputs(self.learner, self.fleet, breaker, config, session, node.stats_period_s)
        recorder = node.recorder_node
        wait_for_recorder(self.outputs.recorded, node.wait_for_recorder_s,
                          rospy.names.resolve_name(recorder) if recorder else "")
        self.router = OffloadRouter(self.learner, *self.sides, STATUSES, config,
                                    on_decision=self.outputs.decision, on_outcome=self.on_outcome,
                                    on_delivered=self.outputs.delivered,
                                    stale=StaleMapCheck(lambda: self.map_info), account=account, breaker=breaker)
        # ~set_parameters: mode, probe rate, hedge and cloud timeout changed on the running node.
        self.reconfigure = LearnerReconfigure(config, self.learner, self.outputs, session.seed)
        rospy.Subscriber("map_metadata", MapMetaData, self.on_map_metadata, queue_size=1)
        latency_topic = node.latency_topic
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
        breaker = self.router.breaker
        was_open = breaker.is_open
        breaker.record_round_trip(msg.source == LinkLatency.HEARTBEAT, msg.reachable, msg.round_trip_s)
        if breaker.is_open != was_open:
            self.outputs.diagnostics.changed()   # a breaker that opened or closed: shown at once

    def build_state(self, request):
        """s_t, or None when it cannot be built (no map metadata yet, a pose that is not finite): such a
        request still goes to the local planner, which names the problem, and teaches nothing."""
        info = self.map_info
        if info is None or self.round_trip_s is None:
            return None
        a, b = request.start.pose.position, request.goal.pose.position
        try:
            d = input_size((a.x, a.y), (b.x, b.y), info.resolution, info.width * info.height)
            return State(input_size=d, cpu_availability=self.cpu.sample(), round_trip_s=self.round_trip_s,
                         local_plan_rate=self.plan_rate.value)
        except (ValueError, RuntimeError, OSError) as error:
            rospy.logwarn("request not learnable: %s", error)
            return None

    def serve(self, request) -> PlanPathResponse:
        arrived = time.perf_counter()    # the router's clock: the caller's latency starts here
        refused = rejection(self.map_info, request)   # refused for its input: answered, never a decision
        if refused is not None:
            self.outputs.rejected(refused)
            rospy.logwarn_throttle(10.0, "request refused (status %d): %s", refused.status, refused.message)
            return PlanPathResponse(status=refused.status, message=refused.message)
        state = self.build_state(request)
        if state is None:
            self.outputs.goal(request.goal)   # no decision: nothing publishes it once the path is delivered
        result = self.router.route(request, state, arrived)
        if result.response is None:
            return PlanPathResponse(status=result.status, message=result.raised)
        if result.note:   # a path on the last map the planner took, never as OK: STALE_MAP and why
            rospy.logwarn_throttle(10.0, "returned a path %s", result.note)
            result.response.status, result.response.message = result.status, result.note
        return result.response

    def on_make_plan(self, request):
        response = self.serve(PlanPathRequest(start=request.start, goal=request.goal, tolerance=request.tolerance))
        return GetPlanResponse(plan=response.path if response.status == PlanPathResponse.OK else Path())

    def on_outcome(self, outcome):
        if self.cpu_window_from_outcome:
            try:
                self.cpu.sample()
            except (OSError, RuntimeError) as error:
                rospy.logwarn_throttle(10, "cannot read the robot's CPU budget: %s", error)
        if outcome.state is None:
            return   # not a decision: nothing to pair it with (the planner's status told the caller why)
        self.plan_rate.observe_outcome(outcome, STATUSES.ok)   # p_t: this request's d_t over its local planning time
        self.outputs.outcome(outcome)

    def shutdown(self):
        if not self.router.wait_idle(10.0):
            rospy.logwarn("the last request did not finish within 10 s")
        self.learner.close()
        self.outputs.close()
        self.fleet.close()
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
