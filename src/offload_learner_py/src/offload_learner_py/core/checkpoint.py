"""Checkpoints of a DQNAgent: weights, optimiser, config and state normalisation in one file, written
atomically (temp file in the same directory, then rename) so a crash never leaves half a model."""
import os
import tempfile
import zipfile

import torch

from offload_learner_py.core.config import DQNConfig
from offload_learner_py.core.dqn import N_ACTIONS, DQNAgent
from offload_learner_py.core.normalisation import OtherStateError, StateNormalisation
from offload_learner_py.core.state import STATE_SIZE

CHECKPOINT_FORMAT = "offload_learner_py.dqn"   # a file format name: kept when the module moved
CHECKPOINT_VERSION = 1
# Bounds checked before anything is unpickled. The weights live in their own zip members; the pickle
# holds only the structure, config and counters (a few KiB). The largest network a config allows
# (config.MAX_PARAMETERS) takes about 320 MB for two networks and Adam's two moments.
MAX_CHECKPOINT_BYTES = 512 * 2 ** 20
MAX_PICKLE_BYTES = 2 ** 20


class IncompatibleCheckpointError(ValueError):
    """The file is not a checkpoint this code can load (other format, version or architecture)."""


TEMP_PREFIX, TEMP_SUFFIX = ".checkpoint-", ".tmp"


def _finite(state_dict) -> bool:
    return all(bool(torch.isfinite(tensor).all()) for tensor in state_dict.values() if torch.is_tensor(tensor))


def remove_orphaned_temps(path: str) -> list:
    """Delete the temp files that saves killed mid-write left beside `path` (call before this process
    saves there: a live save of another process would lose its temp file). Returns what was removed."""
    directory = os.path.dirname(os.path.abspath(path))
    removed = []
    try:
        names = os.listdir(directory)
    except OSError:
        return removed
    for name in names:
        if name.startswith(TEMP_PREFIX) and name.endswith(TEMP_SUFFIX):
            try:
                os.unlink(os.path.join(directory, name))
                removed.append(name)
            except OSError:
                pass
    return removed


def save_checkpoint(agent: DQNAgent, path: str) -> None:
    """Atomic: a temp file in the same directory, fsync, rename. Refuses non-finite weights (a diverged
    network must not replace a good checkpoint); on any failure the temp file is removed and the error raised."""
    for name, network in (("q_network", agent.q_network), ("target_network", agent.target_network)):
        if not _finite(network.state_dict()):
            raise ValueError(f"{name} has non-finite weights: checkpoint {path} not written")
    payload = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "config": agent.config.to_dict(),
        "normalisation": agent.normalisation.to_dict(),
        "normalisation_frozen": agent.normalisation_frozen,
        "steps": agent.steps,
        "gradient_steps": agent.gradient_steps,
        "q_network": agent.q_network.state_dict(),
        "target_network": agent.target_network.state_dict(),
        "optimizer": agent.optimizer.state_dict(),
    }
    directory = os.path.dirname(os.path.abspath(path))
    descriptor, temp_path = tempfile.mkstemp(prefix=TEMP_PREFIX, suffix=TEMP_SUFFIX, dir=directory)
    try:
        with os.fdopen(descriptor, "wb") as temp_file:
            torch.save(payload, temp_file)
            temp_file.flush()
            os.fsync(temp_file.fileno())
        os.replace(temp_path, path)
    except BaseException:
        if os.path.exists(temp_path):
            os.unlink(temp_path)
        raise


def load_checkpoint(path: str, expected_config: DQNConfig = None,
                    max_bytes: int = MAX_CHECKPOINT_BYTES) -> DQNAgent:
    """Rebuild the agent. With expected_config, refuse a checkpoint whose network shape differs. A file
    over max_bytes (on disk or uncompressed), or whose pickle is over MAX_PICKLE_BYTES, is refused before
    it is read."""
    try:
        size = os.path.getsize(path)
    except OSError as error:
        raise IncompatibleCheckpointError(f"{path} is not a readable offload DQN checkpoint: {error}") from error
    if size > max_bytes:
        raise IncompatibleCheckpointError(f"{path}: {size} bytes, over the {max_bytes}-byte cap of a checkpoint")
    try:
        # torch.load does not check the CRCs of the zip members it reads, so damaged weights would load
        # silently; the zip layer does check them.
        with zipfile.ZipFile(path) as archive:
            _check_sizes(archive, path, max_bytes)
            damaged = archive.testzip()
        if damaged is not None:
            raise ValueError(f"member {damaged} fails its CRC check")
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except IncompatibleCheckpointError:
        raise
    except Exception as error:  # torch raises several types for a foreign or corrupt file
        raise IncompatibleCheckpointError(f"{path} is not a readable offload DQN checkpoint (missing, truncated or "
                                          f"corrupt): {error}") from error
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise IncompatibleCheckpointError(f"{path} is not an offload DQN checkpoint (format "
                                          f"{payload.get('format') if isinstance(payload, dict) else None!r})")
    if payload.get("version") != CHECKPOINT_VERSION:
        raise IncompatibleCheckpointError(f"{path} has checkpoint version {payload.get('version')}, this code "
                                          f"reads version {CHECKPOINT_VERSION}; retrain or convert it")
    try:
        config = DQNConfig.from_dict(payload["config"])
        normalisation = StateNormalisation.from_dict(payload["normalisation"])
    except OtherStateError as error:
        raise IncompatibleCheckpointError(f"{path} was trained on another state: {error}; retrain from its bags "
                                          f"(python -m offload_learner_py.offline.retrain)") from error
    except (KeyError, TypeError, ValueError) as error:
        raise IncompatibleCheckpointError(f"{path} has an invalid config or normalisation: {error}") from error
    if expected_config is not None and tuple(expected_config.hidden_sizes) != config.hidden_sizes:
        raise IncompatibleCheckpointError(f"{path} holds a network with hidden layers {list(config.hidden_sizes)}, "
                                          f"expected {list(expected_config.hidden_sizes)}")
    try:
        steps, gradient_steps = _count(payload, "steps"), _count(payload, "gradient_steps")
    except (KeyError, TypeError, ValueError) as error:
        raise IncompatibleCheckpointError(f"{path} has no valid step counters: {error}") from error
    for name in ("q_network", "target_network"):
        _check_shapes(payload.get(name), config, path, name)
        if not _finite(payload[name]):
            raise IncompatibleCheckpointError(f"{path}: {name} holds non-finite weights (a diverged network)")
    agent = DQNAgent(config, normalisation if payload.get("normalisation_frozen", True) else None)
    try:
        agent.q_network.load_state_dict(payload["q_network"])
        agent.target_network.load_state_dict(payload["target_network"])
        agent.optimizer.load_state_dict(payload["optimizer"])
    except (KeyError, IndexError, TypeError, AttributeError, RuntimeError, ValueError) as error:
        raise IncompatibleCheckpointError(f"{path} weights do not fit the network its config describes: "
                                          f"{error}") from error
    agent.steps, agent.gradient_steps = steps, gradient_steps
    return agent


def _count(payload: dict, key: str) -> int:
    value = payload[key]
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ValueError(f"{key} must be a non-negative integer, got {value!r}")
    return value


def _check_sizes(archive: zipfile.ZipFile, path: str, max_bytes: int) -> None:
    """Declared (uncompressed) sizes, from the zip directory, before any member is read."""
    total = 0
    for info in archive.infolist():
        total += info.file_size
        if info.filename.endswith("data.pkl") and info.file_size > MAX_PICKLE_BYTES:
            raise IncompatibleCheckpointError(f"{path}: its pickle {info.filename} is {info.file_size} bytes, over "
                                              f"the {MAX_PICKLE_BYTES}-byte cap (a checkpoint's pickle holds no "
                                              f"weights)")
    if total > max_bytes:
        raise IncompatibleCheckpointError(f"{path}: its members would decompress to {total} bytes, over the "
                                          f"{max_bytes}-byte cap of a checkpoint")


def _check_shapes(state_dict, config: DQNConfig, path: str, name: str) -> None:
    """Every weight the config's network needs, with its shape, before the network is built."""
    if not isinstance(state_dict, dict):
        raise IncompatibleCheckpointError(f"{path} has no {name} weights")
    widths = [STATE_SIZE, *config.hidden_sizes, N_ACTIONS]
    expected = {}
    for i, (width_in, width_out) in enumerate(zip(widths[:-1], widths[1:])):
        expected[f"layers.{2 * i}.weight"] = (width_out, width_in)
        expected[f"layers.{2 * i}.bias"] = (width_out,)
    if set(state_dict) != set(expected):
        raise IncompatibleCheckpointError(f"{path}: weights do not fit the network its config describes "
                                          f"(hidden layers {list(config.hidden_sizes)}): {name} holds "
                                          f"{sorted(state_dict)}, it needs {sorted(expected)}")
    for key, shape in expected.items():
        found = tuple(getattr(state_dict[key], "shape", ()))
        if found != shape:
            raise IncompatibleCheckpointError(f"{path}: weights do not fit the network its config describes "
                                              f"(hidden layers {list(config.hidden_sizes)}): {name} {key} needs "
                                              f"shape {shape}, the file holds {found}")
