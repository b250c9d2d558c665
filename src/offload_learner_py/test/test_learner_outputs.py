"""The learner node's records of a decided request (nodes/learner_outputs.py) without a master, rospy's publishers
and clock replaced by stand-ins: nothing is published on the caller's path (before its planner is called); the goal
and the decision (stamped at its moment) go out once the caller has its path, before a probe's slower side is done,
and the outcome after them."""
import itertools
import logging
import threading
import time

import pytest

pytest.importorskip("offload_msgs.msg", reason="offload_msgs is not built")

import rospy  # noqa: E402
from geometry_msgs.msg import PoseStamped  # noqa: E402
from nav_msgs.msg import Path  # noqa: E402
from offload_msgs.srv import PlanPathRequest, PlanPathResponse  # noqa: E402

from offload_learner_py import LOCAL  # noqa: E402
from offload_learner_py.core.policies import AlwaysLocal  # noqa: E402
from offload_learner_py.nodes import learner_outputs  # noqa: E402
from offload_learner_py.nodes.learner_fleet import NodeFleet  # noqa: E402
from offload_learner_py.nodes.learner_io import STATUSES  # noqa: E402
from offload_learner_py.online.breaker import LinkBreaker  # noqa: E402
from offload_learner_py.online.fleet_link import FleetConfig  # noqa: E402
from offload_learner_py.online.model_guard import GuardConfig  # noqa: E402
from offload_learner_py.online.router_types import DEPLOYED, RouterConfig  # noqa: E402
from offload_learner_py.online.session import SessionConfig  # noqa: E402
from routertools import STATE, wired_router  # noqa: E402


class Published(list):
    """(topic, message) in the order published, on every stand-in publisher."""

    def publisher(self, topic, msg_type, **_):
        class Publisher:
            def publish(_, msg):
                self.append((topic, msg))
        return Publisher()

    def topics(self):
        return [topic for topic, _ in self if topic in ("~goal", "~decision", "~outcome")]


class Diagnostics:
    def __init__(self, *_):
        pass

    def close(self):
        pass


@pytest.fixture
def published(monkeypatch):
    published = Published()
    ticks = itertools.count(1)
    monkeypatch.setattr(rospy, "Publisher", published.publisher)
    monkeypatch.setattr(rospy.Time, "now", staticmethod(lambda: rospy.Time(next(ticks))))
    monkeypatch.setattr(learner_outputs, "NodeDiagnostics", Diagnostics)
    return published


def test_a_decided_requests_records_go_out_after_its_path_not_on_the_callers_path(published):
    seen_by_planner = []

    def planner(request):
        seen_by_planner.append(published.topics())
        return STATUSES.ok, PlanPathResponse(status=PlanPathResponse.OK, path=Path())
    config = RouterConfig(mode=DEPLOYED, probe_rate=0.0, hedge=False, probe_while_warming_up=False)
    session = SessionConfig(policy="local", learn=False)
    fleet = NodeFleet(FleetConfig(), GuardConfig(), DEPLOYED, "local", "", logging.getLogger("test"))
    router = wired_router(AlwaysLocal(), planner, planner, STATUSES, config)
    outputs = learner_outputs.LearnerOutputs(router.learner, fleet, LinkBreaker(config.breaker), config, session, 60.0)
    router.on_decision, router.on_outcome, router.on_delivered = outputs.decision, outputs.outcome, outputs.delivered
    goal = PoseStamped()
    goal.pose.position.x = 4.5
    for _ in range(2):
        response = router.route(PlanPathRequest(goal=goal), STATE)
        assert response.status == STATUSES.ok
        assert router.wait_idle(30)

    assert seen_by_planner == [[], ["~goal", "~decision", "~outcome"]], \
        "a request's goal or decision was published before its planner was called"
    assert published.topics() == ["~goal", "~decision", "~outcome"] * 2
    records = [msg for topic, msg in published if topic in ("~goal", "~decision", "~outcome")]
    for goal_msg, decision, outcome in (records[:3], records[3:]):
        assert goal_msg.pose.position.x == 4.5
        assert decision.request_id == outcome.request_id and decision.action == LOCAL == decision.routed
        assert decision.input_size == STATE.input_size and decision.policy == router.learner.config.policy
        # the decision's stamp is its moment's: before the outcome's
        assert decision.header.stamp < outcome.header.stamp
    assert records[1].request_id + 1 == records[4].request_id


def test_decided_requests_kept_for_their_outcomes_are_bounded(published):
    config = RouterConfig(mode=DEPLOYED)
    session = SessionConfig(policy="local", learn=False)
    fleet = NodeFleet(FleetConfig(), GuardConfig(), DEPLOYED, "local", "", logging.getLogger("test"))
    router = wired_router(AlwaysLocal(), None, None, STATUSES, config)
    outputs = learner_outputs.LearnerOutputs(router.learner, fleet, LinkBreaker(config.breaker), config, session, 60.0)
    from offload_learner_py.core.policies import Decision
    from offload_learner_py.online.router_types import Routing
    for request_id in range(learner_outputs.MAX_UNPAIRED + 50):
        outputs.decision(Routing(request_id, STATE, Decision(LOCAL, 1.0), False, LOCAL, DEPLOYED))
    assert len(outputs._decided) == learner_outputs.MAX_UNPAIRED
    assert min(outputs._decided) == 50, "the oldest are let go first"


def test_the_decision_goes_out_once_the_caller_has_its_path_before_the_slower_side_is_done(published):
    """A client pairs its call with the decision it waits for next (the fault-matrix rostest does): the decision
    must not wait for a probe's slower side, which may take up to the cloud timeout."""
    cloud_may_answer = threading.Event()

    def local(request):
        return STATUSES.ok, PlanPathResponse(status=PlanPathResponse.OK, path=Path())

    def cloud(request):
        assert cloud_may_answer.wait(30)
        return STATUSES.ok, PlanPathResponse(status=PlanPathResponse.OK, path=Path())
    config = RouterConfig(mode="learning", hedge=False)
    session = SessionConfig(policy="local", learn=False)
    fleet = NodeFleet(FleetConfig(), GuardConfig(), "learning", "local", "", logging.getLogger("test"))
    router = wired_router(AlwaysLocal(), local, cloud, STATUSES, config)
    outputs = learner_outputs.LearnerOutputs(router.learner, fleet, LinkBreaker(config.breaker), config, session, 60.0)
    router.on_decision, router.on_outcome, router.on_delivered = outputs.decision, outputs.outcome, outputs.delivered
    try:
        assert router.route(PlanPathRequest(goal=PoseStamped()), STATE).status == STATUSES.ok
        deadline = time.monotonic() + 30
        while "~decision" not in published.topics() and time.monotonic() < deadline:
            time.sleep(0.01)
        assert published.topics() == ["~goal", "~decision"], "the decision waited for the probe's slower side"
    finally:
        cloud_may_answer.set()
    assert router.wait_idle(30)
    assert published.topics() == ["~goal", "~decision", "~outcome"]
