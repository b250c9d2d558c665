"""Where the planner tests find maps: the small MovingAI set bundled in test/data (always there, so a
bare clone tests itself), the maps bundled with the package, and, when present, the larger shared map
set (OFFLOAD_SHARED_MAPS overrides ../shared/data/maps beside the workspace), used in addition."""
import os
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1]
WORKSPACE = PACKAGE.parents[1]
SHARED_MAPS = Path(os.environ.get("OFFLOAD_SHARED_MAPS", WORKSPACE.parent / "shared" / "data" / "maps"))
BUNDLED_MAPS = PACKAGE / "maps"
BUNDLED_MOVINGAI = PACKAGE / "test" / "data" / "movingai"


def _by_set_and_name(*roots, pattern):
    """Files matching `pattern` under each root, keyed by their path below the root so a map in both
    sets is used once (the first root wins)."""
    found = {}
    for root in roots:
        if root.is_dir():
            for path in sorted(root.glob(pattern)):
                found.setdefault(path.relative_to(root).as_posix(), path)
    return found


def movingai_maps():
    """Every MovingAI map to check: the bundled ones, then the shared ones not bundled."""
    return sorted(_by_set_and_name(BUNDLED_MOVINGAI, SHARED_MAPS / "movingai", pattern="*/*.map").values())


def ros_map_yamls():
    """Every map_server YAML to check: the package's bundled maps, then the shared ones not bundled."""
    return sorted(_by_set_and_name(BUNDLED_MAPS, SHARED_MAPS / "ros", pattern="*/*.yaml").values())
