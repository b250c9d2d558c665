"""Where the planner tests find maps: the shared map set (OFFLOAD_SHARED_MAPS overrides
../shared/data/maps beside the workspace) and the maps bundled with the package."""
import os
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1]
WORKSPACE = PACKAGE.parents[1]
SHARED_MAPS = Path(os.environ.get("OFFLOAD_SHARED_MAPS", WORKSPACE.parent / "shared" / "data" / "maps"))
BUNDLED_MAPS = PACKAGE / "maps"
