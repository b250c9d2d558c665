"""Shared fixtures: the map sets in ../shared/data/maps (skipped with a reason when absent) and the maps
bundled with the package."""
import os
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1]
WORKSPACE = PACKAGE.parents[1]
SHARED_MAPS = Path(os.environ.get("OFFLOAD_SHARED_MAPS", WORKSPACE.parent / "shared" / "data" / "maps"))
BUNDLED_MAPS = PACKAGE / "maps"


@pytest.fixture(scope="session")
def shared_maps() -> Path:
    if not SHARED_MAPS.is_dir():
        pytest.skip(f"shared map set not found at {SHARED_MAPS} (set OFFLOAD_SHARED_MAPS)")
    return SHARED_MAPS


@pytest.fixture(scope="session")
def bundled_maps() -> Path:
    return BUNDLED_MAPS
