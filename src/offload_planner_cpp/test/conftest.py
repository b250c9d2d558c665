"""Shared fixtures: the map sets in ../shared/data/maps (skipped with a reason when absent) and the maps
bundled with the package."""
from pathlib import Path

import pytest

from planner_testdata import BUNDLED_MAPS, SHARED_MAPS


@pytest.fixture(scope="session")
def shared_maps() -> Path:
    if not SHARED_MAPS.is_dir():
        pytest.skip(f"shared map set not found at {SHARED_MAPS} (set OFFLOAD_SHARED_MAPS)")
    return SHARED_MAPS


@pytest.fixture(scope="session")
def bundled_maps() -> Path:
    return BUNDLED_MAPS


@pytest.fixture
def key_root(tmp_path):
    """Server keys with an allowlist of two robots (robot, robot2) and their client keys, under tmp_path."""
    from cloud_test_helpers import make_keys
    make_keys(tmp_path, ["robot", "robot2"])
    return tmp_path
