import struct
import zipfile
import zlib

import numpy as np
import pytest

from offload_learner_py.core.state import STATE_SCHEMA, STATE_SIZE
from offload_learner_py.data.dataset import COLUMNS, TABLE_FORMAT, TransitionTable
from offload_learner_py.data.npz_io import save_versioned_npz


def _table(n=20):
    rng = np.random.default_rng(0)
    return TransitionTable(t=np.arange(n), input_size=rng.uniform(0, 1, n), cpu_availability=rng.uniform(0, 1, n),
                           round_trip_s=np.full(n, 0.03), local_plan_rate=10 ** rng.uniform(6, 8, n),
                           local_s=rng.uniform(0.01, 0.1, n),
                           cloud_s=rng.uniform(0.01, 0.1, n), action=rng.integers(0, 2, n),
                           action_propensity=np.full(n, 0.5), reward=rng.uniform(-1, 1, n),
                           metadata={"kind": "test", "seed": 3})


def test_columns_are_the_issue_s_transition_format_with_the_plan_rate():
    assert COLUMNS == ("t", "input_size", "cpu_availability", "round_trip_s", "local_plan_rate", "local_s", "cloud_s",
                       "action", "action_propensity", "reward")


# The paper's three state fields on purpose: a table from before p_t (saved by older code, or data that never
# had it) still reads, with p_t at the schema's value for older records in every row.
PAPER_COLUMNS = tuple(name for name in COLUMNS if name != "local_plan_rate")


def test_a_table_from_before_the_plan_rate_reads_with_its_missing_value(tmp_path):
    table = _table(5)
    old = {name: getattr(table, name) for name in PAPER_COLUMNS}
    missing = STATE_SCHEMA["local_plan_rate"].missing
    save_versioned_npz(str(tmp_path / "old.npz"), TABLE_FORMAT, {"kind": "old"}, old)
    with open(tmp_path / "old.csv", "w") as out:
        out.write(",".join(PAPER_COLUMNS) + "\n")
        for row in zip(*old.values()):
            out.write(",".join(repr(v.item()) for v in row) + "\n")
    for loaded in (TransitionTable(**old), TransitionTable.load_npz(str(tmp_path / "old.npz")),
                   TransitionTable.from_csv(str(tmp_path / "old.csv"))):
        assert loaded.local_plan_rate.tolist() == [missing] * 5
        for name in PAPER_COLUMNS:
            assert np.array_equal(getattr(loaded, name), getattr(table, name))
    with pytest.raises(TypeError, match="missing round_trip_s"):   # a field without a value for older records
        TransitionTable(**{name: values for name, values in old.items() if name != "round_trip_s"})


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
    assert len(part) == 3 and part.states.shape == (3, STATE_SIZE)
    assert np.array_equal(part.states[:, 1], table.cpu_availability[2:5])


def _corrupt_member(path, member, tmp_path):
    """Copies of an .npz with bytes of one compressed member flipped (zip structure left intact)."""
    data = open(path, "rb").read()
    with zipfile.ZipFile(path) as archive:
        info = archive.getinfo(member)
    # the local header's name and extra field lengths (its extra field may differ from the directory's)
    name_length, extra_length = struct.unpack("<HH", data[info.header_offset + 26:info.header_offset + 30])
    start = info.header_offset + 30 + name_length + extra_length
    copies = []
    for offset in (0, info.compress_size // 2):  # the deflate header (zlib.error) and the middle (CRC)
        bad = bytearray(data)
        for i in range(start + offset, start + offset + 8):
            bad[i] ^= 0xFF
        copy = tmp_path / f"corrupt-{offset}.npz"
        copy.write_bytes(bytes(bad))
        copies.append(str(copy))
    return copies


def test_a_corrupt_member_is_a_clear_error(tmp_path):
    good = str(tmp_path / "table.npz")
    _table(200).save_npz(good)
    causes = set()
    for path in _corrupt_member(good, "local_s.npy", tmp_path):
        with pytest.raises(ValueError, match=r"corrupt-\d+\.npz: cannot read transition table: array 'local_s'") \
                as error:
            TransitionTable.load_npz(path)
        causes.add(type(error.value.__cause__))
    assert zlib.error in causes  # the case a damaged deflate stream raised raw before


def test_a_bare_npy_or_text_file_is_not_a_table(tmp_path):
    np.save(str(tmp_path / "bare.npy"), np.arange(3))
    (tmp_path / "text.npz").write_text("t,input_size\n")
    for name in ("bare.npy", "text.npz"):
        with pytest.raises(ValueError, match=f"{name} is not a transition table"):
            TransitionTable.load_npz(str(tmp_path / name))


@pytest.mark.parametrize("name,value,message", [
    ("local_s", np.nan, "local_s must be finite in every row; row 1 is nan"),
    ("cloud_s", np.inf, "cloud_s must be finite in every row; row 1 is inf"),
    ("cloud_s", -0.1, r"cloud_s must be > 0 in every row; row 1 is -0.1"),
    ("action_propensity", np.nan, "action_propensity must be finite"),
    ("action_propensity", 1.5, r"action_propensity must be in \(0, 1\] in every row; row 1"),
    ("reward", np.nan, "reward must be finite"),
    ("reward", -1.5, r"reward must be in \[-1, 1\] in every row; row 1"),
    ("cpu_availability", 1.2, r"cpu_availability must be in \[0, 1\]"),
    ("input_size", -1.0, "input_size must be >= 0"),
    ("round_trip_s", np.nan, "round_trip_s must be finite"),
    ("action", 0.5, "action must hold whole numbers"),
    ("action", 2, "action must be 0 .local. or 1 .cloud. in every row; row 1 is 2"),
    ("t", np.nan, "t must be finite"),
])
def test_every_column_is_validated_naming_column_and_row(tmp_path, name, value, message):
    columns = {column: getattr(_table(3), column) for column in COLUMNS}
    bad = np.array(columns[name], dtype=np.float64)
    bad[1] = value
    with pytest.raises(ValueError, match=message):
        TransitionTable(**{**columns, name: bad})
    # the same rules guard a loaded file, and the error names it
    path = str(tmp_path / "bad.npz")
    np.savez(path, format=np.array("offload_learner_py.transitions/1"), metadata=np.array("{}"), **{**columns, name: bad})
    with pytest.raises(ValueError, match=f"bad.npz: invalid transition table: {message}"):
        TransitionTable.load_npz(path)


def test_non_numeric_and_two_dimensional_columns_are_rejected():
    columns = {column: getattr(_table(3), column) for column in COLUMNS}
    with pytest.raises(ValueError, match="column reward is not numeric"):
        TransitionTable(**{**columns, "reward": np.array(["a", "b", "c"])})
    with pytest.raises(ValueError, match="column reward must be one-dimensional"):
        TransitionTable(**{**columns, "reward": np.zeros((3, 1))})
    with pytest.raises(ValueError, match="columns have different lengths"):
        TransitionTable(**{**columns, "t": np.arange(2)})


def _csv(tmp_path, text, name="table.csv"):
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def test_csv_errors_name_the_file_and_line(tmp_path):
    header = ",".join(COLUMNS) + "\n"
    good = "0,0.1,0.5,0.03,2e7,0.01,0.02,1,0.5,-0.3\n"
    cases = [("", "table.csv is empty"),
             ("t,input_size\n" + good, "table.csv line 1: header t,input_size is not t,input_size,"),
             (header + good + "1,0.1,0.5\n", "table.csv line 3: 3 fields, expected 10"),
             (header + good.strip() + ",7\n", "table.csv line 2: 11 fields, expected 10"),
             ("t,cpu_availability,input_size" + header[12:] + good, "line 1: header t,cpu_availability,input_size,"),
             (header + good.replace("0.01", "fast"), "table.csv line 2: local_s 'fast' is not a number"),
             (header + good + good.replace("0.01", "nan"), "table.csv line 3: invalid transition table: local_s must "
                                                           "be finite in every row; row 1 is nan"),
             (header + good + "\n" + good.replace(",1,", ",3,"), "table.csv line 4: invalid transition table: action")]
    for text, message in cases:
        with pytest.raises(ValueError, match=message):
            TransitionTable.from_csv(_csv(tmp_path, text))
    with pytest.raises(ValueError, match="absent.csv: cannot read transition table"):
        TransitionTable.from_csv(str(tmp_path / "absent.csv"))
    (tmp_path / "binary.csv").write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(ValueError, match="binary.csv: not a text CSV file"):
        TransitionTable.from_csv(str(tmp_path / "binary.csv"))


def test_csv_with_only_a_header_or_float_actions_loads(tmp_path):
    header = ",".join(COLUMNS) + "\n"
    assert len(TransitionTable.from_csv(_csv(tmp_path, header))) == 0
    table = TransitionTable.from_csv(_csv(tmp_path, header + "0.0,0.1,0.5,0.03,2e7,0.01,0.02,1.0,0.5,-0.3\n"))
    assert table.action.dtype == np.int64 and table.action[0] == 1
