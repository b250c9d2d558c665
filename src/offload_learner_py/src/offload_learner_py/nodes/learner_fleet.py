"""The offload_learner node's fleet mode (rospy side): with `~fleet_endpoint` set in deployed mode the robot
decides with the model versions the fleet learner publishes and streams its rows to it (online/fleet.py,
fleet_link.py, model_guard.py: no ROS there; its `~fleet_*` and `~guard_*` parameters are read with the node's
others, nodes/learner_params.py). Here: the rows as the node publishes them (the OffloadDecision and OffloadOutcome messages, serialized by genpy as
rosbag stores them, with the classes' definitions and md5), and the TrainingStats fields of the fleet mode."""
import io
import time

from offload_msgs.msg import OffloadDecision, OffloadOutcome

from offload_learner_py.online.fleet import FleetRobot, make_fleet_robot
from offload_learner_py.online.fleet_link import FleetConfig
from offload_learner_py.online.learning import OnlineLearner
from offload_learner_py.online.model_guard import GuardConfig
from offload_learner_py.online.router_types import DEPLOYED

DEFINITIONS = {"offload_msgs/OffloadDecision": OffloadDecision._full_text,
               "offload_msgs/OffloadOutcome": OffloadOutcome._full_text}
MD5 = {"offload_msgs/OffloadDecision": OffloadDecision._md5sum, "offload_msgs/OffloadOutcome": OffloadOutcome._md5sum}


def serialized(msg) -> bytes:
    out = io.BytesIO()
    msg.serialize(out)
    return out.getvalue()


def encode(row):
    decision, outcome = row
    return serialized(decision), serialized(outcome)


class NodeFleet:
    """The fleet robot of a node, or `robot` None when the node learns itself."""

    def __init__(self, config: FleetConfig, guard: GuardConfig, mode: str, policy: str, model: str, log):
        self.config = config
        self.robot = None
        if not self.config.enabled:
            return
        if mode != DEPLOYED or policy != "dqn":
            log.warning("~fleet_endpoint is for a deployed DQN; %s mode with policy %s learns (or not) on the robot "
                        "as before", mode, policy)
            return
        self.robot: FleetRobot = make_fleet_robot(self.config, guard, model, encode=encode, definitions=DEFINITIONS,
                                                  md5=MD5, log=log)
        log.info("fleet mode: deciding with model %s, rows to %s, version query every %g s",
                 self.robot.policy.version[:12] or "none (local plans until one arrives)", self.config.endpoint,
                 self.config.period_s)

    def learner(self, session, log, **settings) -> OnlineLearner:
        """The node's learner: for a fleet robot one that never trains (its policy does not learn)."""
        if self.robot is None:
            return OnlineLearner.resume(session, log=log, **settings)
        return OnlineLearner(self.robot.policy, settings.pop("statuses"), config=session, log=log, **settings)

    def outcome(self, outcome, msg, decision=None) -> None:
        """Before `msg` is published: the guard's sample (its CPU added to learner_cpu_s), then the row (`decision`,
        `msg`), when the request's decision message is known."""
        if self.robot is None:
            return
        began = time.thread_time()
        self.robot.on_outcome(outcome)
        msg.learner_cpu_s += time.thread_time() - began
        if decision is not None and self.robot.link is not None:
            self.robot.link.enqueue((decision, msg))

    def fill_stats(self, msg):
        if self.robot is not None:
            for name, value in self.robot.stats().items():
                setattr(msg, name, value)
        return msg

    def close(self) -> None:
        if self.robot is not None:
            self.robot.close()
