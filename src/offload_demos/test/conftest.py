"""The learner's, the planner's and the cloud's test helpers (bags, maps, servers) serve the demo's tests too."""
import sys
from pathlib import Path

for package in ("offload_learner_py", "offload_planner_cpp", "offload_cloud"):
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / package / "test"))
