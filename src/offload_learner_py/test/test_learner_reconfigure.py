"""The learner's live settings (online/live_settings.py, behind its dynamic_reconfigure): a change reaches the next
decisions of a running router, is checked by RouterConfig's own rules and refused whole, and the generated
OffloadLearnerConfig names exactly those settings with RouterConfig's defaults and no bounds of its own."""
import ast
import math

import pytest

from offload_learner_py.core.policies import AlwaysCloud, AlwaysLocal
from offload_learner_py.online.live_settings import LIVE, LiveSettings
from offload_learner_py.online.router_types import MODES, RouterConfig

from routertools import STATE, TIMEOUT, FakePlanner, VirtualClock, finish, make_router


def routed(router, recorder, count=3):
    before = len(recorder.routings)
    for _ in range(count):
        router.route("req", STATE)
    assert router.wait_idle(10)
    return recorder.routings[before:]


def test_a_change_reaches_the_next_decisions_of_the_running_router():
    clock = VirtualClock()
    router, recorder = make_router(AlwaysLocal(), FakePlanner(clock, 0.2), FakePlanner(clock, 0.1), clock)
    live = LiveSettings(router.config, router.learner)
    assert not any(r.probe for r in routed(router, recorder))
    assert live.apply({"probe_rate": 1.0}) == {"probe_rate": (0.0, 1.0)}
    assert all(r.probe for r in routed(router, recorder))
    live.apply({"probe_rate": 0.0, "mode": "learning"})
    assert all(r.probe and r.mode == "learning" for r in routed(router, recorder))
    live.apply({"mode": "deployed"})
    assert not any(r.probe or not math.isnan(r.deadline_s) for r in routed(router, recorder))
    live.apply({"hedge": True})
    assert all(r.deadline_s > 0 for r in routed(router, recorder)), "the hedge gives each decision a deadline"
    finish(router)


def test_the_cloud_timeout_is_the_next_failed_requests_l_cloud():
    clock = VirtualClock()
    router, recorder = make_router(AlwaysCloud(), FakePlanner(clock, 0.2), FakePlanner(clock, 0.1, status=TIMEOUT),
                                   clock, timeout_s=5.0)
    LiveSettings(router.config, router.learner).apply({"cloud_timeout_s": 2.5})
    routed(router, recorder, 1)
    finish(router)
    assert recorder.outcomes[-1].cloud_timeout and recorder.outcomes[-1].cloud_s == 2.5


@pytest.mark.parametrize("change, words", [
    ({"probe_rate": 1.5}, "probe_rate must be in [0, 1], got 1.5"),
    ({"probe_rate": math.nan}, "probe_rate must be in [0, 1], got nan"),
    ({"cloud_timeout_s": 0.0}, "cloud_timeout_s must be positive, got 0.0"),
    ({"mode": "greedy", "probe_rate": 0.5}, "mode must be one of learning, deployed, got 'greedy'"),
    ({"probe_rate": "0.5"}, "not supported between"),
])
def test_a_value_routerconfig_refuses_is_refused_and_nothing_changes(change, words):
    """The rules are RouterConfig's, as for a YAML value at start: the same words, and no part of the change kept."""
    config = RouterConfig(probe_rate=0.1)

    class Learner:
        cloud_timeout_s = config.cloud_timeout_s

    live = LiveSettings(config, Learner())
    with pytest.raises(ValueError) as refused:
        live.apply(change)
    assert words in str(refused.value)
    assert live.current() == {"mode": "deployed", "probe_rate": 0.1, "hedge": False, "cloud_timeout_s": 5.0}
    assert Learner.cloud_timeout_s == 5.0
    if not isinstance(change.get("probe_rate"), str):   # the very words RouterConfig refuses it with at start
        with pytest.raises(ValueError) as at_start:
            RouterConfig(**{**live.current(), **change})
        assert str(at_start.value) == str(refused.value)


def test_the_generated_config_names_the_live_settings_with_routerconfigs_defaults_and_no_bounds():
    generated = pytest.importorskip("offload_learner_py.cfg.OffloadLearnerConfig", reason="built by catkin")
    defaults = RouterConfig()
    assert tuple(generated.defaults) == LIVE
    assert generated.defaults == {name: getattr(defaults, name) for name in LIVE}
    # Unbounded: dynamic_reconfigure clamps nothing, so RouterConfig refuses what it refuses.
    assert all(generated.min[name] in (-math.inf, "", False) and generated.max[name] in (math.inf, "", True)
               for name in LIVE)
    mode = next(p for p in generated.config_description["parameters"] if p["name"] == "mode")
    assert tuple(const["value"] for const in ast.literal_eval(mode["edit_method"])["enum"]) == MODES
