"""What the offload_learner node publishes about its work: each request's decision and outcome (the transition
table a bag rebuilds) and its sides' latched paths, the training statistics at most every ~stats_period_s, refused
requests, goals, the latched settings, and its /diagnostics status (online/health.py's rules).

A decided request's goal and decision are published once its caller has its path (the router's on_delivered), not
before its sides are called: a publish on the caller's path (serializing, waking rospy's writer thread, which then
takes the interpreter) cost it 0.2 ms at the median and 1 ms at the 90th percentile on a loaded robot, as much as a
small map's plan. The decision keeps the stamp and model steps of its moment; its outcome follows once no side of
the request is running."""
import threading
import time
from collections import OrderedDict

import rospy
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from offload_msgs.msg import LearnerConfig, OffloadDecision, OffloadOutcome, RequestRejected, TrainingStats

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.nodes.diagnostics import NodeDiagnostics
from offload_learner_py.nodes.learner_io import Every, config_msg, decision_msg, outcome_msg, path_of, stamped, \
    stats_msg
from offload_learner_py.nodes.path_wire import pose_count
from offload_learner_py.online.health import LearnerHealth

MAX_UNPAIRED = 1000     # decided requests whose outcome has not come (requests in flight); more is a leak, not load


class _Decided:
    """One decided request until its outcome: what its decision message needs from its moment, then the message."""
    __slots__ = ("routing", "stamp", "steps", "msg")

    def __init__(self, routing, stamp, steps: int):
        self.routing, self.stamp, self.steps, self.msg = routing, stamp, steps, None


class LearnerOutputs:
    def __init__(self, learner, fleet, breaker, router_config, session, stats_period_s: float):
        self.learner, self.fleet, self.breaker = learner, fleet, breaker
        self.decision_pub = rospy.Publisher("~decision", OffloadDecision, queue_size=100)
        self.outcome_pub = rospy.Publisher("~outcome", OffloadOutcome, queue_size=100)
        self.stats_pub = rospy.Publisher("~stats", TrainingStats, queue_size=10)
        self.stats_due = Every(stats_period_s)
        self.path_pubs = {LOCAL: rospy.Publisher("~path_local", Path, queue_size=1, latch=True),
                          CLOUD: rospy.Publisher("~path_cloud", Path, queue_size=1, latch=True)}
        self.path_empty = {LOCAL: False, CLOUD: False}
        self.goal_pub = rospy.Publisher("~goal", PoseStamped, queue_size=10, latch=True)
        self.config_pub = rospy.Publisher("~config", LearnerConfig, queue_size=1, latch=True)
        self.rejected_pub = rospy.Publisher("~rejected", RequestRejected, queue_size=100)
        self.config_pub.publish(config_msg(router_config, learner, session.seed, router_config.weights.alpha))
        self.health = LearnerHealth(router_config.mode, session.policy)
        self._decided = OrderedDict()   # request id -> _Decided
        self._lock = threading.Lock()   # the delivering side thread and the finishing one may be two
        self.diagnostics = NodeDiagnostics("offload decisions", self.health_status)

    @property
    def recorded(self):
        """The publishers a recorder must hear before the node serves."""
        return self.decision_pub, self.outcome_pub

    def health_status(self):
        robot = self.fleet.robot
        return self.health.status(self.breaker.is_open, self.breaker.reason, robot.stats() if robot else None,
                                  time.monotonic())

    def rejected(self, refused) -> None:
        self.rejected_pub.publish(stamped(RequestRejected(status=refused.status, message=refused.message)))

    def goal(self, goal) -> None:
        self.goal_pub.publish(goal)

    def decision(self, routing) -> None:
        """On the caller's path (the router's on_decision): what the records need from this moment, nothing sent."""
        self.health.decision(routing.action == CLOUD, routing.probe)
        with self._lock:
            self._decided[routing.request_id] = _Decided(routing, rospy.Time.now(), self.learner.policy.steps)
            while len(self._decided) > MAX_UNPAIRED:
                self._decided.popitem(last=False)

    def delivered(self, routing) -> None:
        """Once the caller has its path (the router's on_delivered): the request's goal and decision."""
        with self._lock:
            self._publish_decision(routing.request_id)

    def _publish_decision(self, request_id: int):
        """Under _lock: the request's goal and decision, once (kept for the fleet's row); the decision or None."""
        decided = self._decided.get(request_id)
        if decided is None:
            return None   # not decided here, or let go by the bound
        if decided.msg is None:
            decided.msg = decision_msg(decided.routing, self.learner.config.policy, decided.steps)
            decided.msg.header.stamp = decided.stamp
            goal = getattr(decided.routing.request, "goal", None)
            if goal is not None:
                self.goal_pub.publish(goal)
            self.decision_pub.publish(decided.msg)
        return decided.msg

    def outcome(self, outcome) -> None:
        """A decided request's outcome (its decision first if a probe's other side finished before the hook ran), its
        sides' paths and, when due, the statistics."""
        msg = outcome_msg(outcome)
        self.health.outcome(outcome.learner_cpu_s)
        with self._lock:
            decision = self._publish_decision(outcome.request_id)
            self._decided.pop(outcome.request_id, None)
        self.fleet.outcome(outcome, msg, decision)   # the guard's sample and the row for the fleet learner
        self.outcome_pub.publish(msg)
        # Each side's latched path is this request's (a probe's losing side too), or empty: never a stale one. An
        # empty one already latched is not sent again (a deployed robot's other side, request after request).
        for action, side in ((LOCAL, outcome.local), (CLOUD, outcome.cloud)):
            path = path_of(side)
            empty = pose_count(path) == 0
            if not (empty and self.path_empty[action]):
                self.path_pubs[action].publish(path)
            self.path_empty[action] = empty
        if self.stats_due():   # the learner counted this request and saved when due
            self.stats()

    def stats(self) -> None:
        self.stats_pub.publish(self.fleet.fill_stats(stats_msg(self.learner)))

    def close(self) -> None:
        """After the last request: the diagnostics stop, the last counts go out whatever the period left unsent."""
        self.diagnostics.close()
        try:
            self.stats()
        except rospy.ROSException as error:
            rospy.logwarn("last ~stats not sent: %s", error)
