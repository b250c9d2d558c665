"""Crafted learner files: every loader bounds what it reads before reading it and
answers with its own error naming the file. The files are built small; memory is checked with tracemalloc
(numpy and the zip layer report their buffers to it), never with a clock."""
import io
import json
import tracemalloc
import zipfile

import numpy as np
import pytest
import torch

from offload_learner_py.core import checkpoint

from offload_learner_py.data import npz_io
from offload_learner_py.core.checkpoint import IncompatibleCheckpointError, load_checkpoint, save_checkpoint
from offload_learner_py.core.config import DQNConfig
from offload_learner_py.data.dataset import COLUMNS, TABLE_FORMAT, TransitionTable
from offload_learner_py.core.dqn import DQNAgent
from offload_learner_py.data.trace import PlanningTrace


def _good_columns(n=20):
    rng = np.random.default_rng(0)
    return {"t": np.arange(n), "input_size": rng.uniform(0, 1, n), "cpu_availability": rng.uniform(0.5, 0.7, n),
            "round_trip_s": np.full(n, 0.03), "local_s": rng.uniform(0.01, 0.1, n),
            "cloud_s": rng.uniform(0.01, 0.1, n), "action": np.zeros(n, np.int64),
            "action_propensity": np.full(n, 0.5), "reward": np.zeros(n)}


def _npy_bytes(array):
    out = io.BytesIO()
    np.lib.format.write_array(out, np.asarray(array), allow_pickle=False)
    return out.getvalue()


def _write_table_npz(path, replace=None, metadata="{}"):
    """A transition-table .npz written member by member, so one member can be forged."""
    replace = replace or {}
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("format.npy", _npy_bytes(np.array(TABLE_FORMAT)))
        archive.writestr("metadata.npy", _npy_bytes(np.array(metadata)))
        for name, values in _good_columns().items():
            archive.writestr(name + ".npy", replace.get(name, _npy_bytes(values)))


def _lying_header(rows, data_bytes=160):
    """An .npy member whose header claims `rows` float64 rows but which holds data_bytes of data."""
    out = io.BytesIO()
    np.lib.format.write_array_header_1_0(out, {"descr": "<f8", "fortran_order": False, "shape": (rows,)})
    return out.getvalue() + bytes(data_bytes)


def _peak_mib(load, *args, **kwargs):
    tracemalloc.start()
    try:
        with pytest.raises(ValueError) as error:
            load(*args, **kwargs)
        return tracemalloc.get_traced_memory()[1] / 2 ** 20, error.value
    finally:
        tracemalloc.stop()


def test_the_loaders_read_a_well_formed_forged_file(tmp_path):
    path = str(tmp_path / "good.npz")
    _write_table_npz(path)
    assert len(TransitionTable.load_npz(path)) == 20  # the forging helper itself writes valid files


def test_a_header_claiming_1e12_rows_is_refused_before_allocating(tmp_path):
    path = str(tmp_path / "rows.npz")
    _write_table_npz(path, replace={"local_s": _lying_header(10 ** 12)})
    peak, error = _peak_mib(TransitionTable.load_npz, path)
    assert "rows.npz" in str(error) and "'local_s'" in str(error) and "1000000000000" in str(error)
    assert peak < 16


def test_a_header_that_disagrees_with_its_member_size_is_refused(tmp_path):
    path = str(tmp_path / "short.npz")
    _write_table_npz(path, replace={"reward": _lying_header(21)})  # 21 rows claimed, 20 rows of data
    with pytest.raises(ValueError, match=r"short.npz: .*'reward'.* 168 bytes of data.* holds 160"):
        TransitionTable.load_npz(path)


def test_deeply_nested_metadata_is_refused_without_recursing(tmp_path):
    path = str(tmp_path / "deep.npz")
    _write_table_npz(path, metadata="[" * 100_000 + "]" * 100_000)
    with pytest.raises(ValueError, match=r"deep.npz: cannot read transition table: its metadata nests deeper than"):
        TransitionTable.load_npz(path)
    # Brackets inside JSON strings are text, not nesting.
    _write_table_npz(path, metadata=json.dumps({"note": "[" * 1000}))
    assert TransitionTable.load_npz(path).metadata == {"note": "[" * 1000}


def _write_zip_bomb_member(archive, name, uncompressed_mib):
    with archive.open(name, "w", force_zip64=True) as member:
        member.write(_lying_header(uncompressed_mib * 2 ** 17, data_bytes=0))
        chunk = bytes(2 ** 20)
        for _ in range(uncompressed_mib):
            member.write(chunk)


def test_a_zip_bomb_is_refused_from_its_declared_size(tmp_path):
    # 48 MiB of zeros deflate to about 48 KiB: the loader is given a 16 MiB cap so the file stays small.
    bomb = str(tmp_path / "bomb.npz")
    with zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("format.npy", _npy_bytes(np.array(TABLE_FORMAT)))
        archive.writestr("metadata.npy", _npy_bytes(np.array("{}")))
        for name, values in _good_columns().items():
            if name != "local_s":
                archive.writestr(name + ".npy", _npy_bytes(values))
        _write_zip_bomb_member(archive, "local_s.npy", 48)
    peak, error = _peak_mib(TransitionTable.load_npz, bomb, max_member_bytes=16 * 2 ** 20)
    assert "bomb.npz" in str(error) and "'local_s'" in str(error) and "16 MiB cap" in str(error)
    assert peak < 8
    # The default cap exists and is what the loaders use.
    assert npz_io.MAX_MEMBER_BYTES <= 2 ** 30


def test_a_trace_loader_applies_the_same_bounds(tmp_path, small_trace):
    good = str(tmp_path / "trace.npz")
    small_trace.save_npz(good)
    forged = str(tmp_path / "forged.npz")
    with zipfile.ZipFile(good) as source, zipfile.ZipFile(forged, "w", zipfile.ZIP_DEFLATED) as out:
        for info in source.infolist():
            data = _lying_header(10 ** 12) if info.filename == "local_s.npy" else source.read(info)
            out.writestr(info.filename, data)
    with pytest.raises(ValueError, match=r"forged.npz: cannot read planning trace: array 'local_s'"):
        PlanningTrace.load_npz(forged)


def test_a_csv_larger_than_the_cap_is_refused_before_parsing(tmp_path):
    path = tmp_path / "big.csv"
    path.write_text(",".join(COLUMNS) + "\n" + "0,0.1,0.5,0.03,2e7,0.1,0.1,0,0.5,0\n" * 2000)
    assert len(TransitionTable.from_csv(str(path))) == 2000
    with pytest.raises(ValueError, match=r"big.csv: .*over the 10240-byte cap"):
        TransitionTable.from_csv(str(path), max_bytes=10 * 2 ** 10)


# --- checkpoints ------------------------------------------------------------------------------------

SMALL = DQNConfig(hidden_sizes=(8, 8), batch_size=4, learning_starts=4)


def _rewrite_member(path, out_path, member_suffix, transform):
    with zipfile.ZipFile(path) as source, zipfile.ZipFile(out_path, "w", zipfile.ZIP_STORED) as out:
        for info in source.infolist():
            data = source.read(info)
            out.writestr(info, transform(data) if info.filename.endswith(member_suffix) else data)


def test_a_checkpoint_whose_pickle_is_padded_is_refused(tmp_path):
    good = str(tmp_path / "good.pt")
    save_checkpoint(DQNAgent(SMALL), good)
    padded = str(tmp_path / "padded.pt")
    # Bytes after the pickle's STOP opcode are ignored by the unpickler: without a bound this loads.
    _rewrite_member(good, padded, "data.pkl", lambda data: data + bytes(checkpoint.MAX_PICKLE_BYTES + 1))
    peak, error = _peak_mib(load_checkpoint, padded)
    assert isinstance(error, IncompatibleCheckpointError)
    assert "padded.pt" in str(error) and "data.pkl" in str(error)
    assert peak < checkpoint.MAX_PICKLE_BYTES / 2 ** 20
    assert load_checkpoint(good).config == SMALL


def test_a_checkpoint_larger_than_its_cap_is_refused(tmp_path):
    path = str(tmp_path / "big.pt")
    save_checkpoint(DQNAgent(SMALL), path)
    with pytest.raises(IncompatibleCheckpointError, match=r"big.pt: .*over the 1024-byte cap"):
        load_checkpoint(path, max_bytes=2 ** 10)


def test_a_checkpoint_config_that_describes_a_huge_network_is_refused_before_building_it(tmp_path):
    path = str(tmp_path / "huge.pt")
    save_checkpoint(DQNAgent(SMALL), path)
    payload = torch.load(path, weights_only=True)
    payload["config"]["hidden_sizes"] = [60000, 60000, 60000]  # 7.2e9 weights, about 29 GB per network
    torch.save(payload, path)
    peak, error = _peak_mib(load_checkpoint, path)
    assert isinstance(error, IncompatibleCheckpointError) and "huge.pt" in str(error)
    assert "60000" in str(error)
    assert peak < 64


def test_a_checkpoint_whose_weights_do_not_match_its_config_is_refused_before_building(tmp_path, monkeypatch):
    path = str(tmp_path / "mismatch.pt")
    save_checkpoint(DQNAgent(SMALL), path)
    payload = torch.load(path, weights_only=True)
    payload["config"]["hidden_sizes"] = [8, 9]
    torch.save(payload, path)
    built = []
    monkeypatch.setattr(checkpoint, "DQNAgent", lambda *args, **kwargs: built.append(args) or DQNAgent(*args))
    with pytest.raises(IncompatibleCheckpointError, match=r"mismatch.pt: .*layers.2.weight.* \(9, 8\).* \(8, 8\)"):
        load_checkpoint(path)
    assert built == []


def test_config_refuses_a_network_too_large_to_build():
    with pytest.raises(ValueError, match="hidden_sizes .* parameters"):
        DQNConfig(hidden_sizes=(60000, 60000, 60000))
    DQNConfig(hidden_sizes=(1024, 1024, 1024))  # large but sane networks stay allowed
