"""Shared fixtures: the map sets in ../shared/data/maps (skipped with a reason when absent) and the maps
bundled with the package. The cloud package's test helpers serve the planner's agreement tests."""
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "offload_cloud" / "test"))

from planner_testdata import BUNDLED_MAPS, SHARED_MAPS


@pytest.fixture(scope="session")
def shared_maps() -> Path:
    if not SHARED_MAPS.is_dir():
        pytest.skip(f"shared map set not found at {SHARED_MAPS} (set OFFLOAD_SHARED_MAPS)")
    return SHARED_MAPS


@pytest.fixture(scope="session")
def bundled_maps() -> Path:
    return BUNDLED_MAPS

