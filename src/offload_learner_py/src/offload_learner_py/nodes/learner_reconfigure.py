"""dynamic_reconfigure of the offload_learner node (cfg/OffloadLearner.cfg, generated at build time): ~set_parameters
changes the mode, the probe rate, the hedge and the cloud timeout of the running node. A change is checked by
online/live_settings.py (RouterConfig's rules, the YAML's); a refused one keeps the settings in force and logs why;
an accepted one is republished on the latched ~config (offload_msgs/LearnerConfig, which launch/record.launch
records), so a bag shows when it came into force, and the /diagnostics status names the new mode."""
import rospy
from dynamic_reconfigure.server import Server

from offload_learner_py.cfg import OffloadLearnerConfig   # the generated module is the type
from offload_learner_py.nodes.learner_io import config_msg
from offload_learner_py.online.live_settings import LiveSettings

FIRST_CALL = ~0   # the level of the server's first call, with the parameters the node started with


class LearnerReconfigure:
    def __init__(self, router_config, learner, outputs, seed: int):
        self.config, self.learner, self.outputs, self.seed = router_config, learner, outputs, seed
        self.settings = LiveSettings(router_config, learner)
        self.server = Server(OffloadLearnerConfig, self.on_request)

    def on_request(self, requested, level):
        """The server's callback: returns the settings in force, which it publishes on ~parameter_updates."""
        if level != FIRST_CALL:   # the first call: the node already runs with what it read at start
            try:
                changed = self.settings.apply(requested)
            except ValueError as error:
                rospy.logwarn("reconfigure refused: %s; the settings in force are kept", error)
                changed = {}
            if changed:
                self.outputs.health.mode = self.config.mode
                self.outputs.config_pub.publish(config_msg(self.config, self.learner, self.seed,
                                                           self.config.weights.alpha))
                rospy.loginfo("reconfigured: %s", ", ".join(f"{name} {old} -> {new}"
                                                            for name, (old, new) in changed.items()))
        requested.update(self.settings.current())
        return requested
