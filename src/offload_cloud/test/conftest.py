"""Shared fixtures: CURVE keys for a server and two robots. The planner's test data (maps) serve here too."""
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "offload_planner_cpp" / "test"))


@pytest.fixture
def key_root(tmp_path):
    """Server keys with an allowlist of two robots (robot, robot2) and their client keys, under tmp_path."""
    from cloud_test_helpers import make_keys
    make_keys(tmp_path, ["robot", "robot2"])
    return tmp_path
