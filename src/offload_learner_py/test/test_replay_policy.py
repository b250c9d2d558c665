"""The replay policy: request k takes the k-th action of its list, in the order the router asks; a bad file is
refused with its name; the node's ~policy replay needs ~replay_actions."""
import pytest

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.replay_policy import ReplayPolicy
from offload_learner_py.core.state import State
from offload_learner_py.online.session import SessionConfig, make_policy

STATE = State(1.0, 0.5, 0.05, 0.0)


def test_each_decision_takes_the_next_action_of_the_file(tmp_path):
    path = tmp_path / "actions.txt"
    path.write_text("# oracle of a probe run\n0\n1\n\n1\n0  # a comment\n")
    policy, agent = make_policy(SessionConfig(policy="replay", replay_actions=str(path)))
    assert agent is None and isinstance(policy, ReplayPolicy)
    assert [policy.decide(STATE).action for _ in range(4)] == [LOCAL, CLOUD, CLOUD, LOCAL]
    assert [policy.decide(STATE).action for _ in range(2)] == [LOCAL, LOCAL] and policy.beyond == 2


def test_bad_files_and_a_missing_file_parameter_are_refused(tmp_path):
    for text in ("0\n2\n", "0\nx\n", "\n# nothing\n"):
        path = tmp_path / "bad.txt"
        path.write_text(text)
        with pytest.raises(ValueError):
            ReplayPolicy.from_file(str(path))
    with pytest.raises(ValueError, match="replay_actions"):
        SessionConfig(policy="replay")


def test_a_file_over_the_bound_is_refused_before_it_is_read_whole(tmp_path, monkeypatch):
    monkeypatch.setattr(ReplayPolicy, "MAX_FILE_BYTES", 64)
    path = tmp_path / "huge.txt"
    path.write_text("0\n" * 40)   # 80 bytes
    with pytest.raises(ValueError, match="over"):
        ReplayPolicy.from_file(str(path))
    path.write_text("1\n" * 32)   # 64 bytes: at the bound, read
    assert len(ReplayPolicy.from_file(str(path)).actions) == 32
