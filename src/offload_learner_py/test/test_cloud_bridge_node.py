"""The cloud bridge node's start-up with a bad key file: it fails at once, naming the file, without a
traceback (the ROS-free key checks are the cloud package's, test_cloud_keys.py)."""
import subprocess
import sys

import pytest

from offload_cloud import keys

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[2] / "offload_cloud" / "test"))
from cloud_test_helpers import make_keys  # noqa: E402


@pytest.fixture
def key_root(tmp_path):
    make_keys(tmp_path, ["robot"])
    return tmp_path


def _strip_secret(path) -> None:
    path.write_text("".join(line for line in path.read_text().splitlines(True) if "secret-key" not in line))


# The node's start-up path without a ROS master: rospy's calls replaced by stand-ins, spin() for 3 s.
NODE_START = """
import sys, time, types, rospy
params = {"~endpoint": "tcp://127.0.0.1:9", "~keys_dir": sys.argv[1], "~heartbeat_period_s": 0.2}
rospy.init_node = rospy.on_shutdown = rospy.loginfo = rospy.logwarn = lambda *a, **k: None
rospy.get_param = lambda name, default=None: params.get(name, default)
rospy.logfatal = lambda fmt, *a: print("FATAL " + fmt % a, file=sys.stderr)
rospy.Publisher = lambda *a, **k: types.SimpleNamespace(publish=lambda msg: None)
rospy.Subscriber = lambda *a, **k: types.SimpleNamespace(resolved_name="map")
rospy.Service = lambda *a, **k: None
rospy.spin = lambda: time.sleep(3)
from offload_learner_py.nodes import cloud_bridge
cloud_bridge.main()
"""


def test_bridge_node_start_up_fails_fast_naming_the_key_file(key_root):
    robot_secret = key_root / "robot" / keys.CLIENT_SECRET
    _strip_secret(robot_secret)
    node = subprocess.run([sys.executable, "-c", NODE_START, str(key_root / "robot")], capture_output=True,
                          text=True, timeout=60)
    assert node.returncode == 1, node.stderr
    assert node.stderr.startswith("FATAL ") and str(robot_secret) in node.stderr and "Traceback" not in node.stderr


@pytest.fixture
def node_parameters(monkeypatch):
    """read_parameters() without a master: `params` are the node's private parameters."""
    import rospy
    params = {"~endpoint": "tcp://127.0.0.1:9", "~insecure": True}
    monkeypatch.setattr(rospy, "get_param", lambda name, default=None: params.get(name, default))
    return params


def test_bridge_node_reads_every_planner_parameter_of_the_cores_table(node_parameters):
    from offload_learner_py.nodes import cloud_bridge
    from offload_planner_cpp import options_table
    rows = [row for row in options_table() if row["node_parameter"]]
    assert cloud_bridge.read_parameters().planner_parameters() == {row["name"]: row["default"] for row in rows}
    changed = {"lethal_threshold": 101, "unknown_is_obstacle": False, "algorithm": "astar", "any_angle": True,
               "cost_factor": 3.0, "neutral_cost": 40.0, "robot_radius": 0.3, "inflation_radius": 0.9,
               "cost_scaling_factor": 2.5}
    assert set(changed) == {row["name"] for row in rows}
    node_parameters.update({"~" + name: value for name, value in changed.items()})
    assert cloud_bridge.read_parameters().planner_parameters() == changed


@pytest.mark.parametrize("name, value", [("lethal_threshold", 0), ("algorithm", "bfs"), ("robot_radius", -1.0),
                                         ("neutral_cost", 0.0), ("cost_scaling_factor", float("nan"))])
def test_bridge_node_refuses_a_planner_parameter_in_the_cores_words(node_parameters, name, value):
    from offload_learner_py.nodes import cloud_bridge
    from offload_planner_cpp import validate_options
    with pytest.raises(ValueError) as core:
        validate_options(**{name: value})
    node_parameters["~" + name] = value
    with pytest.raises(ValueError) as node:
        cloud_bridge.read_parameters()
    assert str(node.value) == "~" + str(core.value)
