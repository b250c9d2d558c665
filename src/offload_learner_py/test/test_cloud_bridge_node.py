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
