"""Workspace-level checks: the cores stay free of ROS, contracts are written once, every package declares
what its code imports, and every launch file loads."""
import ast
import os
import re
import subprocess
import sys
import xml.etree.ElementTree as ElementTree
from pathlib import Path

import pytest

WORKSPACE = Path(__file__).resolve().parents[1]
PLANNER = WORKSPACE / "src" / "offload_planner_cpp"
# The planner's ROS layer; every other source and header of the package is the core, so a new file is checked
# unless it is named here (a hand list of the core missed path_check.h/.cpp once).
ROS_LAYER = {"planner_ros.h", "planner_reconfigure.h", "planner_ros.cpp", "planner_node.cpp", "planner_diagnostics.cpp",
             "planner_reconfigure.cpp"}
CORE_SOURCES = sorted(path for folder in (PLANNER / "include" / "offload_planner_cpp", PLANNER / "src")
                      for path in folder.iterdir() if path.suffix in (".h", ".cpp") and path.name not in ROS_LAYER)
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


# What ships to a robot or a cloud host, and the subpackages of it that may use ROS (the rospy nodes).
SHIPPED = {"offload_planner_cpp": {"nodes"}, "offload_cloud": set(), "offload_learner_py": {"nodes"}}


def shipped_modules(package, with_ros=False):
    """Dotted names and paths of every module of a package, walked (not listed by hand); without its rospy
    nodes unless with_ros."""
    root = WORKSPACE / "src" / package / "src" / package
    for path in sorted(root.rglob("*.py")):
        parts = path.relative_to(root).with_suffix("").parts
        if not with_ros and parts[0] in SHIPPED.get(package, ()):
            continue
        yield ".".join((package,) + parts).removesuffix(".__init__"), path


@pytest.mark.parametrize("package", sorted(SHIPPED))
def test_ros_free_libraries_import_without_ros(package):
    """Every module of a shipped package outside its rospy nodes imports in an interpreter where any ROS
    import fails, and none names rospy or roslib in its text either (a lazy import inside a function)."""
    modules = {name: path for name, path in shipped_modules(package) if not name.endswith(".__main__")}
    assert len(modules) >= {"offload_planner_cpp": 2, "offload_cloud": 15, "offload_learner_py": 30}[package]
    done = run_without_ros("".join(f"import {name}\n" for name in modules))
    assert done.returncode == 0, done.stderr
    named = [name for name, path in modules.items()
             if re.search(r"^\s*(import|from)\s+(rospy|roslib|rosbag)\b", path.read_text(), re.M)]
    assert not named, f"ROS imported in a ROS-free module: {named}"


def test_the_ros_free_guard_fails_on_a_ros_import():
    done = run_without_ros("import rospy")
    assert done.returncode != 0 and "ROS import in a ROS-free core" in done.stderr


def test_planner_python_core_plans_without_ros():
    done = run_without_ros("import numpy, offload_planner_cpp\n"
                           "r = offload_planner_cpp.plan(numpy.zeros((3, 3), numpy.int8), (0, 0), (2, 2))\n"
                           "print(round(r.cost, 6))")
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "2.828427"


@pytest.mark.parametrize("package", sorted(SHIPPED))
def test_nothing_shipped_imports_the_demos_package(package):
    for name, path in shipped_modules(package, with_ros=True):
        imported = set(imported_modules(path))
        assert "offload_demos" not in imported, f"{name} imports offload_demos, which does not ship"
        assert "devtools" not in path.read_text(), f"{name} mentions devtools"


def local_imports(package):
    """module -> the modules of the same package it imports at module level or in functions."""
    names = dict(shipped_modules(package, with_ros=True))
    graph = {}
    for name, path in names.items():
        found = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                candidates = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                candidates = [node.module] + [f"{node.module}.{alias.name}" for alias in node.names]
            else:
                continue
            found |= {c for c in candidates if c in names and c != name}
        graph[name] = found
    return graph


def cycle_in(graph):
    """One import cycle of `graph` as a list of modules, or None (a package __init__ importing its own
    submodules is not a cycle)."""
    state, stack = {}, []

    def visit(node):
        state[node] = "open"
        stack.append(node)
        for other in sorted(graph[node]):
            if node.startswith(other + "."):
                continue   # a submodule's import of its parent package runs the parent first anyway
            if state.get(other) == "open":
                return stack[stack.index(other):] + [other]
            if other not in state and (found := visit(other)):
                return found
        state[node] = "done"
        stack.pop()
        return None

    for node in sorted(graph):
        if node not in state and (found := visit(node)):
            return found
    return None


@pytest.mark.parametrize("package", sorted(SHIPPED) + ["offload_demos"])
def test_no_import_cycle_inside_a_package(package):
    cycle = cycle_in(local_imports(package))
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_the_cycle_check_finds_a_cycle():
    assert cycle_in({"a.x": {"a.y"}, "a.y": {"a.z"}, "a.z": {"a.x"}}) == ["a.x", "a.y", "a.z", "a.x"]
    assert cycle_in({"a.x": {"a.y"}, "a.y": set()}) is None


def test_no_c_header_include_cycle():
    include = PLANNER / "include" / "offload_planner_cpp"
    graph = {h.name: set(re.findall(r'#include "offload_planner_cpp/(\w+\.h)"', h.read_text())) for h in include.glob("*.h")}
    cycle = cycle_in(graph)
    assert cycle is None, "header include cycle: " + " -> ".join(cycle)


def python_modules():
    return sorted(p for p in (WORKSPACE / "src").rglob("*.py") if "/test/" not in str(p)) + \
        sorted((WORKSPACE / "tools").glob("*.py"))


def test_no_module_over_400_lines_and_nodes_thin():
    long = [f"{p.relative_to(WORKSPACE)}: {n}" for p in python_modules()
            if (n := len(p.read_text().splitlines())) > 400]
    assert not long, "modules over 400 lines: " + ", ".join(long)
    learner_node = WORKSPACE / "src/offload_learner_py/src/offload_learner_py/nodes/learner.py"
    assert len(learner_node.read_text().splitlines()) < 200, "the learner node is to stay under 200 lines"


@pytest.mark.parametrize("package", ["offload_learner_py", "offload_demos"])
def test_python_node_scripts_are_two_line_entry_points(package):
    scripts = WORKSPACE / "src" / package / "scripts"
    for script in scripts.iterdir():
        lines = script.read_text().splitlines()
        if lines[0] != "#!/usr/bin/env python3":
            continue   # robot_confine is a shell launch-prefix, not a node
        assert len(lines) == 3, f"{script.name} is more than an import and a call"
        assert re.fullmatch(r"from (offload_learner_py\.nodes|offload_demos)\.\w+ import (\w+)", lines[1]), lines[1]
        assert lines[2] == lines[1].split()[-1] + "()"


def loaded(launch_file):
    """The launch (or rostest) file as roslaunch reads it, its arguments at their defaults."""
    import roslaunch.config
    import roslaunch.xmlloader
    config = roslaunch.config.ROSLaunchConfig()
    roslaunch.xmlloader.XmlLoader().load(str(launch_file), config, verbose=False)
    return config


@pytest.mark.parametrize("launch_file", sorted((WORKSPACE / "launch").glob("*.launch")), ids=lambda p: p.name)
def test_launch_files_load(launch_file):
    assert loaded(launch_file).nodes, f"{launch_file.name} starts no node"


LAUNCHED = sorted([*(WORKSPACE / "launch").glob("*.launch"), *(WORKSPACE / "test").glob("*.test"),
                   *(WORKSPACE / "src").glob("*/test/*.test")], key=str)


@pytest.mark.parametrize("launch_file", LAUNCHED, ids=lambda p: str(p.relative_to(WORKSPACE)))
def test_every_node_a_launch_or_rostest_file_starts_is_installed(launch_file):
    """roslaunch finds each node's executable through its package's package.xml: a Debian package that ships the
    binary but not the package.xml (libdiagnostic-aggregator-tools without -dev) fails only when a launch starts it."""
    import roslib.packages
    import rospkg
    config = loaded(launch_file)
    for node in [*config.nodes, *config.tests]:
        try:
            found = roslib.packages.find_node(node.package, node.type)
        except (roslib.packages.ROSPkgException, rospkg.ResourceNotFound) as error:
            found, why = [], str(error).splitlines()[0]
        else:
            why = "no such executable in it"
        assert found, f"{launch_file.name}: node {node.package}/{node.type}: {why}"


PYTHON_SOURCES = sorted(p for p in (WORKSPACE / "src").rglob("*.py") if "/test/" not in str(p))
STATUS_NAMES = ("NO_MAP", "BAD_FRAME", "START_OFF_MAP", "GOAL_OFF_MAP", "START_BLOCKED", "GOAL_BLOCKED",
                "NO_PATH", "INVALID_MAP", "CLOUD_TIMEOUT", "CLOUD_ERROR", "INVALID_REQUEST")
TYPED_STATUS = re.compile(r"\b(%s)\b\s*[=:]\s*\d" % "|".join(STATUS_NAMES))
CONTRACT_DEFINITIONS = re.compile(r"def\s+(world_to_cell|cell_to_world|validate_map|in_map_frame|yaw_of)\b|"
                                  r"math\.floor\(")


def test_status_codes_and_the_request_contract_are_not_retyped_in_python():
    """The codes live in plan_status.h (and, of necessity, PlanPath.srv, checked against them by a
    static_assert and test_request_contract.py); world <-> cell conversion and request checks live in
    plan_request.h. No Python module types either again."""
    for source in PYTHON_SOURCES:
        for number, line in enumerate(source.read_text().splitlines(), start=1):
            assert not TYPED_STATUS.search(line), f"{source}:{number} types a status code: {line.strip()}"
            assert not CONTRACT_DEFINITIONS.search(line), f"{source}:{number} re-implements the contract: {line}"


# Top-level Python modules to the rosdep keys that provide them.
ROSDEP_KEYS = {"numpy": "python3-numpy", "zmq": "python3-zmq", "yaml": "python3-yaml", "PIL": "python3-pil",
               "scipy": "python3-scipy", "matplotlib": "python3-matplotlib", "torch": "python3-torch",
               "rosbags": "python3-rosbags-pip", "tqdm": "python3-tqdm", "rospy": "rospy", "rosbag": "rosbag",
               "prometheus_client": "python3-prometheus-client",
               "roslaunch": "roslaunch", "rostest": "rostest", "tf2_ros": "tf2_ros", "genpy": "genpy",
               "nav_msgs": "nav_msgs", "geometry_msgs": "geometry_msgs", "std_msgs": "std_msgs",
               "offload_msgs": "offload_msgs", "offload_planner_cpp": "offload_planner_cpp", "offload_cloud": "offload_cloud",
               "offload_learner_py": "offload_learner_py", "rosgraph_msgs": "rosgraph_msgs",
               "sensor_msgs": "sensor_msgs", "visualization_msgs": "visualization_msgs", "rosgraph": "rosgraph", "roslib": "roslib",
               "atheris": "python3-atheris-pip", "rospkg": "python3-rospkg", "rosunit": "rosunit",
               "lz4": "python3-lz4", "offload_demos": "offload_demos", "diagnostic_updater": "diagnostic_updater",
               "diagnostic_msgs": "diagnostic_msgs", "dynamic_reconfigure": "dynamic_reconfigure"}


def imported_modules(source: Path):
    for node in ast.walk(ast.parse(source.read_text())):
        if isinstance(node, ast.Import):
            yield from (alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            yield node.module.split(".")[0]


@pytest.mark.parametrize("package", sorted(p.parent for p in (WORKSPACE / "src").glob("*/package.xml")),
                         ids=lambda p: p.name)
def test_package_xml_declares_what_the_code_imports(package):
    manifest = ElementTree.parse(package / "package.xml").getroot()
    run = {e.text for e in manifest if e.tag in ("depend", "exec_depend")}
    test_only = {e.text for e in manifest if e.tag == "test_depend"}
    missing = []
    for source in sorted((package / "src").rglob("*.py")) + sorted((package / "scripts").glob("*")):
        if source.suffix not in ("", ".py") or "__pycache__" in str(source):
            continue
        if source.suffix == "" and "python" not in source.read_text().split("\n", 1)[0]:
            continue   # a shell script
        # The demos package (demo and test tools) may lean on test dependencies; everything else ships.
        allowed = run | test_only if package.name == "offload_demos" else run
        for module in set(imported_modules(source)):
            if module in sys.stdlib_module_names or module in ("_core", package.name):
                continue
            key = ROSDEP_KEYS.get(module)
            assert key, f"{source}: no rosdep key known for import {module}: add it to ROSDEP_KEYS"
            if key not in allowed:
                missing.append(f"{source.relative_to(package)} imports {module}: declare {key}")
    assert not missing, "package.xml misses run dependencies:\n" + "\n".join(missing)


def test_ros_free_pip_install_plans_serves_and_pings(tmp_path):
    """What a cloud host runs: `pip install ./src/offload_planner_cpp ./src/offload_cloud` into a venv without
    ROS installs the core, the cloud package and its commands, and none of the rospy nodes or demo tools; the
    declared dependencies are enough to load a map_server map (YAML + PGM)."""
    venv = tmp_path / "venv"
    # Nothing of the sourced workspace (PYTHONPATH, ROS_*) may leak in: a host without ROS.
    env = {name: value for name, value in os.environ.items()
           if not name.startswith(("ROS", "PYTHON", "CMAKE", "PKG_CONFIG", "LD_LIBRARY", "CATKIN"))}
    subprocess.run(["/usr/bin/python3", "-m", "venv", str(venv)], check=True, env=env)
    python = str(venv / "bin" / "python")
    # As README_cloud says: pyzmq built on the system's libzmq, whose libsodium is the fast one.
    built = subprocess.run([python, "-m", "pip", "install", "-q", "--no-binary", "pyzmq", str(PLANNER),
                            str(WORKSPACE / "src" / "offload_cloud")],
                           capture_output=True, text=True, env=env)
    assert built.returncode == 0, built.stderr[-3000:]
    code = ("import importlib.util, subprocess, sys, numpy as np, offload_planner_cpp\n"
            "assert importlib.util.find_spec('rospy') is None\n"
            "assert importlib.util.find_spec('offload_planner_cpp.nodes') is None\n"
            "assert importlib.util.find_spec('offload_demos') is None\n"
            "assert importlib.util.find_spec('offload_learner_py') is None\n"
            "from offload_cloud.server import CloudServer, ServerConfig\n"
            "from offload_cloud.client import CloudClient\n"
            "from offload_planner_cpp.maps import load_map\n"
            f"assert load_map({str(PLANNER / 'maps' / 'turtlebot3_world' / 'map.yaml')!r}).grid.shape == (384, 384)\n"
            "from offload_cloud.curve_speed import bundled_libsodium\n"
            "assert not bundled_libsodium()\n"
            "server = CloudServer(ServerConfig(bind='tcp://127.0.0.1:0', insecure=True, workers=1))\n"
            "endpoint = server.start()\n"
            "client = CloudClient(endpoint, insecure=True, timeout_s=10)\n"
            "reply = client.plan(np.zeros((5, 5), np.int8), (0, 0), (4, 4)).reply\n"
            "ping = subprocess.run([sys.executable, '-m', 'offload_cloud.client', endpoint, '--ping',\n"
            "                       '--insecure'], capture_output=True, text=True)\n"
            "helped = subprocess.run([sys.executable.rsplit('/', 1)[0] + '/offload-cloud-server', '--help'],\n"
            "                        capture_output=True, text=True)\n"
            "assert helped.returncode == 0 and '--keys-dir' in helped.stdout, helped.stderr\n"
            "client.close(); server.stop()\n"
            "print(int(reply.status), round(reply.cost_cells, 6), ping.returncode)\n")
    done = subprocess.run([python, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=120, env=env)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["0", "5.656854", "0"]
    for command in ("offload-cloud-server", "offload-cloud-ping", "offload-cloud-keys"):
        assert (venv / "bin" / command).exists(), command
    assert not (venv / "bin" / "offload-wan-emulator").exists()
