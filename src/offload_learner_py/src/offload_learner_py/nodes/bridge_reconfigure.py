"""The cloud bridge node follows the local planner's dynamic_reconfigure: the planner options a request carries to
the cloud are the ones the local planner node plans with, so `dynparam set /planner inflation_radius 0.3` reaches
both sides of every offloading decision. It listens to the planner's latched ~parameter_updates (which a bag records)
and hands each update's planner options to CloudBridge.set_planner_parameters, which checks them by the core's
options table: one refused keeps the options in force. The first update, latched, brings the planner's options in
force at start: they win over the bridge's own, as both sides must plan alike."""
import rospy
from dynamic_reconfigure.msg import Config


def values_of(msg: Config) -> dict:
    """{name: value} of an update (dynamic_reconfigure.encoding's decode_config without its groups; that module loads
    its package's manifest through rosdep, a line on stderr on a host whose rosdep was never initialised)."""
    return {param.name: param.value for param in (*msg.bools, *msg.ints, *msg.strs, *msg.doubles)}


class PlannerUpdates:
    def __init__(self, bridge, topic: str):
        """`topic`: the local planner's ~parameter_updates; "" follows nothing."""
        self.bridge = bridge
        self.subscriber = rospy.Subscriber(topic, Config, self.on_update, queue_size=10) if topic else None

    def on_update(self, msg) -> None:
        values = values_of(msg)
        before = self.bridge.config.planner_parameters()
        wanted = {name: values[name] for name in before if name in values}
        try:
            changed = self.bridge.set_planner_parameters(wanted)
        except (ValueError, TypeError) as error:
            rospy.logwarn("planner options from %s refused: %s; the options in force are kept",
                          self.subscriber.resolved_name, error)
            return
        if changed:
            rospy.loginfo("planner options from %s: %s", self.subscriber.resolved_name,
                          ", ".join(f"{name} {before[name]} -> {value}" for name, value in changed.items()))
