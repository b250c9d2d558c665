"""The deployed model as a file a robot loads without pickle: the greedy network's layers and the state
normalisation it was trained with, in one .npz, named by the SHA-256 of its bytes (its version).

The fleet learner on the cloud host writes it (`model_bytes`); the robot fetches it, checks the bytes
against the version it asked for, and loads it weights-only (`load_model`: numpy with pickle refused, every
array's shape and finiteness checked, the normalisation's state fields against this code's schema) into a
FastDecision, the compiled forward pass it decides with. A file that fails any check raises ModelFileError and
the robot keeps the model it has."""
import hashlib
import io
import json
import zipfile
from typing import Optional, Sequence

import numpy as np

from offload_learner_py.core.normalisation import OtherStateError, StateNormalisation

FORMAT = "offload-model-1"
MAX_MODEL_BYTES = 16 << 20     # the 3 x 256 network is about 0.5 MB; a file far larger is not a model
MAX_LAYERS = 16
MAX_WIDTH = 4096


class ModelFileError(ValueError):
    """A model file that is not one: wrong hash, not an npz, pickled content, bad shapes or values."""


def model_version(data: bytes) -> str:
    """The version of a model file: the SHA-256 of its bytes, hex."""
    return hashlib.sha256(data).hexdigest()


def model_bytes(weights: Sequence[np.ndarray], biases: Sequence[np.ndarray],
                normalisation: StateNormalisation) -> bytes:
    """The .npz bytes of a network given as (in x out) weight matrices and bias vectors, input layer first.
    Deterministic: the same model gives the same bytes, so the same version."""
    arrays = {"format": np.array(FORMAT), "normalisation": np.array(json.dumps(normalisation.to_dict(),
                                                                              sort_keys=True))}
    for k, (w, b) in enumerate(zip(weights, biases)):
        arrays[f"weight_{k}"] = np.ascontiguousarray(w, dtype=np.float32)
        arrays[f"bias_{k}"] = np.ascontiguousarray(b, dtype=np.float32)
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as archive:
        for name in sorted(arrays):   # fixed order and timestamps: identical models, identical bytes
            member = io.BytesIO()
            np.lib.format.write_array(member, arrays[name], allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            archive.writestr(info, member.getvalue())
    return out.getvalue()


def agent_model_bytes(agent) -> bytes:
    """model_bytes of a DQNAgent's online network and normalisation."""
    fast = agent.fast_decision()
    return model_bytes(fast.weights, fast.biases, agent.normalisation)


def load_model(data: bytes, expected_version: Optional[str] = None):
    """(FastDecision, StateNormalisation) of a model file; ModelFileError when it is not a valid one."""
    from offload_learner_py.core.dqn import FastDecision

    if not isinstance(data, (bytes, bytearray, memoryview)) or len(data) > MAX_MODEL_BYTES:
        raise ModelFileError(f"a model file is at most {MAX_MODEL_BYTES} bytes")
    data = bytes(data)
    if expected_version is not None and model_version(data) != expected_version:
        raise ModelFileError(f"the file's SHA-256 {model_version(data)[:12]} is not the version asked for "
                             f"{expected_version[:12]}")
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as archive:
            members = archive.infolist()
            if len(members) > 2 * MAX_LAYERS + 2 or sum(m.file_size for m in members) > MAX_MODEL_BYTES:
                raise ModelFileError("the archive declares more than a model holds")
        with np.load(io.BytesIO(data), allow_pickle=False) as npz:
            arrays = {name: npz[name] for name in npz.files}
    except ModelFileError:
        raise
    except (ValueError, OSError, zipfile.BadZipFile, KeyError, EOFError) as error:
        raise ModelFileError(f"not a model file: {error}") from None
    if str(arrays.get("format", "")) != FORMAT:
        raise ModelFileError(f"not a {FORMAT} file")
    try:
        normalisation = StateNormalisation.from_dict(json.loads(str(arrays["normalisation"])))
    except OtherStateError as error:
        raise ModelFileError(f"a model of another state: {error}") from None
    except (KeyError, ValueError, TypeError) as error:
        raise ModelFileError(f"bad normalisation: {error}") from None
    weights, biases = [], []
    width = len(normalisation.mean)
    for k in range(MAX_LAYERS + 1):
        if f"weight_{k}" not in arrays:
            break
        w, b = arrays[f"weight_{k}"], arrays.get(f"bias_{k}")
        if (b is None or w.dtype != np.float32 or b.dtype != np.float32 or w.ndim != 2 or b.ndim != 1
                or w.shape[0] != width or w.shape[1] != b.shape[0] or not 0 < w.shape[1] <= MAX_WIDTH):
            raise ModelFileError(f"layer {k}: shapes {getattr(w, 'shape', None)} / {getattr(b, 'shape', None)} "
                                 f"do not chain from a width of {width}")
        if not (np.isfinite(w).all() and np.isfinite(b).all()):
            raise ModelFileError(f"layer {k} holds values that are not finite")
        weights.append(w)
        biases.append(b)
        width = w.shape[1]
    if not weights or len(weights) > MAX_LAYERS or width != 2:
        raise ModelFileError(f"the network must end in 2 action values, got {len(weights)} layers ending in {width}")
    return FastDecision(weights, biases, normalisation), normalisation
