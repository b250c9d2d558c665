"""The learner's settings an operator changes on a running robot (dynamic_reconfigure: nodes/learner_reconfigure.py):
the mode, the probe rate, the hedge and the cloud timeout, all RouterConfig fields and node parameters of the same
names. A change is checked by RouterConfig's own rules, the ones a YAML value meets at start (a new RouterConfig is
built with it), and is applied whole or not at all."""
import dataclasses
from typing import Any, Dict, Mapping, Tuple

from offload_learner_py.online.router_types import RouterConfig

LIVE = ("mode", "probe_rate", "hedge", "cloud_timeout_s")


class LiveSettings:
    """`config` is the RouterConfig the router, its side caller and the node's outputs share: an accepted change is
    written into it, so the next request is routed with it; `learner.cloud_timeout_s` (l_cloud of a failed cloud
    call, learning.py) follows cloud_timeout_s."""

    def __init__(self, config: RouterConfig, learner):
        self.config, self.learner = config, learner

    def current(self) -> Dict[str, Any]:
        return {name: getattr(self.config, name) for name in LIVE}

    def apply(self, requested: Mapping[str, Any]) -> Dict[str, Tuple[Any, Any]]:
        """Applies the LIVE values of `requested` (others are ignored) and returns {name: (old, new)} of those that
        changed. ValueError, in RouterConfig's words, when RouterConfig refuses one: then nothing changes."""
        wanted = {name: requested[name] for name in LIVE if name in requested}
        try:
            checked = dataclasses.replace(self.config, **wanted)    # RouterConfig.__post_init__ raises
        except TypeError as error:   # a value of another type (text for a number) compared with a bound
            raise ValueError(f"refused {wanted}: {error}") from None
        changed = {name: (getattr(self.config, name), getattr(checked, name)) for name in LIVE
                   if getattr(checked, name) != getattr(self.config, name)}
        for name, (_, value) in changed.items():
            setattr(self.config, name, value)    # one attribute at a time: a request routed meanwhile sees old or new
        self.learner.cloud_timeout_s = self.config.cloud_timeout_s
        return changed
