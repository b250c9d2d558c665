"""Change the state schema and the consumers follow: a copy of the package whose core/state.py moves every
field, changes bounds and adds a field (with a log-scale hint and a value for older records) is run in a
fresh interpreter (schema_variant.py), which checks State, the transition table (.npz, CSV), normalisation,
the network's input width, the fast decision, checkpoints, the evaluation's reading of u_t and d_t, the
summary, the LSTM and off-policy features, the records and their bounds, bags of the old and the new
definition, and the decision message."""
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

from offload_learner_py.core.checkpoint import save_checkpoint
from offload_learner_py.core.dqn import DQNAgent
from offload_learner_py.core.normalisation import StateNormalisation
from offload_learner_py.core.state import STATE_SIZE

HERE = Path(__file__).resolve().parent
PACKAGE = HERE.parent / "src" / "offload_learner_py"
ANCHOR = "STATE_FIELDS = STATE_SCHEMA.names\n"
VARIANT = '''import dataclasses as _dataclasses
_PAPER = STATE_SCHEMA
STATE_SCHEMA = StateSchema((
    StateField("rate", "r_t", "1/s", "a field for the test: some rate of the robot", low=0.0, high=1000.0,
               recorded_max=100.0, log_floor=1e-3, missing=2.0),
    _dataclasses.replace(_PAPER["round_trip_s"], high=10.0, recorded_max=5.0),
    _dataclasses.replace(_PAPER["input_size"], recorded_max=50.0),
    _PAPER["cpu_availability"],
    _PAPER["local_plan_rate"],
))
'''


def variant_package(parent: Path) -> Path:
    """A copy of the package with the changed schema in core/state.py."""
    copy = parent / "offload_learner_py"
    shutil.copytree(PACKAGE, copy, ignore=shutil.ignore_patterns("__pycache__", "*.npz"))
    state_py = copy / "core" / "state.py"
    text = state_py.read_text()
    assert text.count(ANCHOR) == 1, "core/state.py no longer derives STATE_FIELDS from STATE_SCHEMA at one place"
    state_py.write_text(text.replace(ANCHOR, VARIANT + ANCHOR))
    return parent


def test_the_consumers_follow_a_changed_schema(tmp_path):
    states = np.random.default_rng(0).uniform(0.1, 0.9, (50, STATE_SIZE))
    paper_checkpoint = tmp_path / "paper.pt"
    save_checkpoint(DQNAgent(normalisation=StateNormalisation.fit(states)), str(paper_checkpoint))
    parent = variant_package(tmp_path / "variant")
    work = tmp_path / "work"
    work.mkdir()
    env = {**os.environ, "PYTHONDONTWRITEBYTECODE": "1", "OMP_NUM_THREADS": "1"}
    run = subprocess.run([sys.executable, str(HERE / "schema_variant.py"), str(parent), str(paper_checkpoint),
                          str(work)], env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stdout + run.stderr
    assert run.stdout.strip() == ("checked: state, table, normalisation, evaluation, baselines, records, bags, "
                                  "decision message")
