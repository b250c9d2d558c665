"""Workspace-level checks: the cores stay free of ROS, and every launch file loads."""
import re
import subprocess
import sys
from pathlib import Path

import pytest

WORKSPACE = Path(__file__).resolve().parents[1]
PLANNER = WORKSPACE / "src" / "offload_planner_cpp"
CORE_SOURCES = [PLANNER / "include" / "offload_planner_cpp" / "dijkstra.h",
                PLANNER / "include" / "offload_planner_cpp" / "map_geometry.h",
                PLANNER / "src" / "dijkstra.cpp", PLANNER / "src" / "bindings.cpp"]
ROS_INCLUDE = re.compile(r'#\s*include\s*[<"](ros/|nav_msgs/|geometry_msgs/|std_msgs/|offload_msgs/|tf2)')


@pytest.mark.parametrize("source", CORE_SOURCES, ids=lambda p: p.name)
def test_planner_core_includes_no_ros_header(source):
    for number, line in enumerate(source.read_text().splitlines(), start=1):
        assert not ROS_INCLUDE.search(line), f"{source.name}:{number} includes ROS: {line.strip()}"
    # Local includes must be core headers too.
    for header in re.findall(r'#include "offload_planner_cpp/(\w+\.h)"', source.read_text()):
        assert PLANNER / "include" / "offload_planner_cpp" / header in CORE_SOURCES


def run_without_ros(code):
    """Runs `code` in a fresh interpreter where importing rospy, roslib or any ROS message fails."""
    guard = ("import sys\n"
             "class NoRos:\n"
             "    def find_spec(self, name, path=None, target=None):\n"
             "        if name.split('.')[0] in {'rospy', 'roslib', 'rosbag', 'genpy', 'nav_msgs', 'std_msgs',\n"
             "                                  'geometry_msgs', 'offload_msgs'}:\n"
             "            raise ImportError('ROS import in a ROS-free core: ' + name)\n"
             "sys.meta_path.insert(0, NoRos())\n")
    return subprocess.run([sys.executable, "-c", guard + code], capture_output=True, text=True)


def test_planner_python_core_imports_without_ros():
    done = run_without_ros("import offload_planner_cpp, offload_planner_cpp.maps, offload_planner_cpp.movingai\n"
                           "import numpy; r = offload_planner_cpp.plan(numpy.zeros((3, 3), numpy.int8), (0, 0), (2, 2))\n"
                           "print(round(r.cost, 6))")
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "2.828427"


def test_learner_core_imports_without_rospy():
    """Every module outside the `nodes` subpackage is the ROS-free core; rospy lives in `nodes` only."""
    package = WORKSPACE / "src" / "offload_learner_py" / "src" / "offload_learner_py"
    modules = sorted(p.stem for p in package.glob("*.py") if p.stem != "__init__")
    assert modules, "learner core has no modules"
    done = run_without_ros("".join(f"import offload_learner_py.{m}\n" for m in modules))
    assert done.returncode == 0, done.stderr
    outside = [p.name for p in package.glob("*.py") if re.search(r"^\s*(import|from)\s+rospy", p.read_text(), re.M)]
    assert not outside, f"rospy imported outside offload_learner_py.nodes: {outside}"
    nodes = sorted((package / "nodes").glob("*.py"))
    assert any("import rospy" in p.read_text() for p in nodes), "the nodes subpackage holds the rospy nodes"


def test_learner_scripts_are_two_line_entry_points():
    scripts = WORKSPACE / "src" / "offload_learner_py" / "scripts"
    for script in scripts.iterdir():
        lines = script.read_text().splitlines()
        if lines[0] != "#!/usr/bin/env python3":
            continue   # robot_confine is a shell launch-prefix, not a node
        assert len(lines) == 3, f"{script.name} is more than an import and a call"
        assert re.fullmatch(r"from offload_learner_py\.nodes\.\w+ import (\w+)", lines[1]), lines[1]
        assert lines[2] == lines[1].split()[-1] + "()"


@pytest.mark.parametrize("launch_file", sorted((WORKSPACE / "launch").glob("*.launch")), ids=lambda p: p.name)
def test_launch_files_load(launch_file):
    import roslaunch.config
    import roslaunch.xmlloader
    config = roslaunch.config.ROSLaunchConfig()
    roslaunch.xmlloader.XmlLoader().load(str(launch_file), config, verbose=False)
    assert config.nodes, f"{launch_file.name} starts no node"
