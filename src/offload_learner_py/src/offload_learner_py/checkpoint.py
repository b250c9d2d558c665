"""Checkpoints of a DQNAgent: weights, optimiser, config and state normalisation in one file, written
atomically (temp file in the same directory, then rename) so a crash never leaves half a model."""
import os
import tempfile
import zipfile

import torch

from offload_learner_py.config import DQNConfig
from offload_learner_py.dqn import DQNAgent
from offload_learner_py.normalisation import StateNormalisation

CHECKPOINT_FORMAT = "offload_learner_py.dqn"
CHECKPOINT_VERSION = 1


class IncompatibleCheckpointError(ValueError):
    """The file is not a checkpoint this code can load (other format, version or architecture)."""


def save_checkpoint(agent: DQNAgent, path: str) -> None:
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
    descriptor, temp_path = tempfile.mkstemp(prefix=".checkpoint-", suffix=".tmp", dir=directory)
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


def load_checkpoint(path: str, expected_config: DQNConfig = None) -> DQNAgent:
    """Rebuild the agent. With expected_config, refuse a checkpoint whose network shape differs."""
    try:
        # torch.load does not check the CRCs of the zip members it reads, so damaged weights would load
        # silently; the zip layer does check them.
        with zipfile.ZipFile(path) as archive:
            damaged = archive.testzip()
        if damaged is not None:
            raise ValueError(f"member {damaged} fails its CRC check")
        payload = torch.load(path, map_location="cpu", weights_only=True)
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
    except (KeyError, TypeError, ValueError) as error:
        raise IncompatibleCheckpointError(f"{path} has an invalid config or normalisation: {error}") from error
    if expected_config is not None and tuple(expected_config.hidden_sizes) != config.hidden_sizes:
        raise IncompatibleCheckpointError(f"{path} holds a network with hidden layers {list(config.hidden_sizes)}, "
                                          f"expected {list(expected_config.hidden_sizes)}")
    try:
        steps, gradient_steps = _count(payload, "steps"), _count(payload, "gradient_steps")
    except (KeyError, TypeError, ValueError) as error:
        raise IncompatibleCheckpointError(f"{path} has no valid step counters: {error}") from error
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
