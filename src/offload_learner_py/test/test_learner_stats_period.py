"""The learner node's ~stats period (nodes/learner_io.Every, ~stats_period_s): at most one TrainingStats a period,
the first at once, every request with 0, and a period it cannot use refused. Without a master."""
import math

import pytest

pytest.importorskip("offload_msgs.msg", reason="offload_msgs is not built")

from offload_learner_py.nodes.learner_io import Every  # noqa: E402
from offload_learner_py.nodes.learner_params import LearnerNodeConfig, read_learner_parameters  # noqa: E402
from test_breaker import Clock  # noqa: E402


def test_at_most_once_a_period_and_the_first_at_once():
    clock = Clock()
    due = Every(1.0, clock)
    sent = []
    for step in range(32):             # a request every 0.125 s (exact in binary) for 4 s
        sent.append(due())
        clock.now += 0.125
    assert [i for i, s in enumerate(sent) if s] == [0, 8, 16, 24]


def test_a_period_of_zero_is_every_request():
    clock = Clock()
    due = Every(0.0, clock)
    assert all(due() for _ in range(5))


def test_the_parameter_reaches_the_node_config_and_bad_values_are_refused():
    settings = read_learner_parameters(lambda name, default: {"stats_period_s": 2.5}.get(name, default))
    assert settings.node.stats_period_s == 2.5
    assert LearnerNodeConfig().stats_period_s == 1.0
    for bad in (-1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="stats_period_s"):
            LearnerNodeConfig(stats_period_s=bad)
