import numpy as np
import pytest

from offload_learner_py.dataset import COLUMNS, TransitionTable


def _table(n=20):
    rng = np.random.default_rng(0)
    return TransitionTable(t=np.arange(n), input_size=rng.uniform(0, 1, n), cpu_availability=rng.uniform(0, 1, n),
                           round_trip_s=np.full(n, 0.03), local_s=rng.uniform(0.01, 0.1, n),
                           cloud_s=rng.uniform(0.01, 0.1, n), action=rng.integers(0, 2, n),
                           action_propensity=np.full(n, 0.5), reward=rng.uniform(-1, 1, n),
                           metadata={"kind": "test", "seed": 3})


def test_columns_are_the_issue_s_transition_format():
    assert COLUMNS == ("t", "input_size", "cpu_availability", "round_trip_s", "local_s", "cloud_s", "action",
                       "action_propensity", "reward")


def test_npz_round_trip(tmp_path):
    table = _table()
    path = str(tmp_path / "table.npz")
    table.save_npz(path)
    loaded = TransitionTable.load_npz(path)
    for name in COLUMNS:
        assert np.array_equal(getattr(loaded, name), getattr(table, name))
    assert loaded.metadata == {"kind": "test", "seed": 3}


def test_corrupt_missing_and_foreign_files_are_clear_errors(tmp_path):
    good = str(tmp_path / "table.npz")
    _table().save_npz(good)
    data = open(good, "rb").read()
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="cannot read transition table"):
        TransitionTable.load_npz(str(truncated))
    with pytest.raises(ValueError, match="cannot read transition table"):
        TransitionTable.load_npz(str(tmp_path / "absent.npz"))
    foreign = str(tmp_path / "foreign.npz")
    np.savez(foreign, t=np.arange(3))
    with pytest.raises(ValueError, match="not a transition table"):
        TransitionTable.load_npz(foreign)


def test_csv_export_round_trips_exactly(tmp_path):
    table = _table()
    path = str(tmp_path / "table.csv")
    table.to_csv(path)
    assert open(path).readline().strip() == ",".join(COLUMNS)
    loaded = TransitionTable.from_csv(path)
    for name in COLUMNS:
        assert np.array_equal(getattr(loaded, name), getattr(table, name))


def test_invalid_tables_are_rejected(tmp_path):
    good = {name: getattr(_table(3), name) for name in COLUMNS}
    for name, value in [("action", [0, 1, 2]), ("local_s", [0.1, 0.0, 0.1]), ("action_propensity", [0.5, 0, 1]),
                        ("t", [0, 1])]:
        with pytest.raises(ValueError):
            TransitionTable(**{**good, name: np.array(value)})
    np.savez(str(tmp_path / "other.npz"), x=np.zeros(3))
    with pytest.raises(ValueError, match="not a transition table"):
        TransitionTable.load_npz(str(tmp_path / "other.npz"))


def test_slice_and_states():
    table = _table(10)
    part = table.slice(2, 5)
    assert len(part) == 3 and part.states.shape == (3, 3)
    assert np.array_equal(part.states[:, 1], table.cpu_availability[2:5])
