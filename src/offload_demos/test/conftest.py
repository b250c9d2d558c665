"""The learner's test helpers (bags written by the tests) serve the demo's tests too."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "offload_learner_py" / "test"))
