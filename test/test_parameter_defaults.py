"""Each node parameter's default is stated once: a field of the node's config dataclasses (the planner node:
the core's options table, and its code for its own three). The nodes read `~name` with that field's default as the
fallback (the same tables feed this test), the README tables are checked against the dataclasses, the YAML
files in launch/config hold only what a deployment overrides, and no launch file restates a default. A
default changed in one place only fails here."""
import ast
import math
import re
import xml.etree.ElementTree as ElementTree
from pathlib import Path

import pytest
import yaml

from offload_cloud.bridge import BridgeConfig
from offload_learner_py.core.config import EXPERIMENT_SCHEDULE, DQNConfig
from offload_learner_py.nodes import cloud_bridge, learner_params, params
from offload_learner_py.online.router_types import RouterConfig
from offload_learner_py.online.session import SessionConfig
from offload_planner_cpp.nodes.map_publisher import MapPublisherConfig
from offload_demos import goal_generator, tools

WORKSPACE = Path(__file__).resolve().parents[1]
LEARNER = WORKSPACE / "src" / "offload_learner_py"
PLANNER = WORKSPACE / "src" / "offload_planner_cpp"
DEMOS = WORKSPACE / "src" / "offload_demos"
LAUNCH = WORKSPACE / "launch"
CONFIG = LAUNCH / "config"



def cpp_node_defaults() -> dict:
    """planner_node's own parameters beside the core's options: their defaults in its code (a literal fallback
    in planner_ros.cpp, or the member's initialiser in planner_ros.h)."""
    source = (PLANNER / "src/planner_ros.cpp").read_text()
    found = {name: yaml.safe_load(value) for name, value in
             re.findall(r'param(?:<[\w:]+>)?\(\s*"(\w+)"\s*,\s*\w+\s*,\s*(-?[\d.]+|true|false|"[^"]*")\s*\)', source)}
    header = (PLANNER / "include/offload_planner_cpp/planner_ros.h").read_text()
    found.update({name: int(value) for name, value in re.findall(r"int (planning_threads)_ = (\d+);", header)})
    return found


def planner_node_defaults() -> dict:
    return {**cloud_bridge.planner_defaults(), **cpp_node_defaults()}


def bridge_defaults() -> dict:
    return {**params.defaults(cloud_bridge.PARAMETERS), **params.defaults(cloud_bridge.NODE_PARAMETERS),
            **cloud_bridge.planner_defaults()}


# node: (README, its section heading, {~name: default} of every parameter it reads, required parameters (no
# default), the YAML file of its overrides and the section in it)
NODES = {
    "offload_learner": (LEARNER / "README.md", "### offload_learner",
                        lambda: params.defaults(learner_params.PARAMETERS),
                        (), CONFIG / "learner.yaml", None),
    "cloud_bridge": (LEARNER / "README.md", "### cloud_bridge", bridge_defaults, ("endpoint",),
                     CONFIG / "cloud_bridge.yaml", "cloud_bridge"),
    "goal_generator": (DEMOS / "README.md", "### goal_generator", lambda: params.defaults(goal_generator.PARAMETERS),
                       (), CONFIG / "goal_generator.yaml", None),
    "robot_workload": (DEMOS / "README.md", "### robot_workload",
                       lambda: params.defaults(tools.WORKLOAD_PARAMETERS), (), CONFIG / "workload.yaml", None),
    "planner": (PLANNER / "README.md", "### planner_node", planner_node_defaults, (), CONFIG / "planner.yaml",
                "planner"),
    "map_publisher": (PLANNER / "README.md", "### map_publisher",
                      lambda: {name: getattr(MapPublisherConfig, name)
                               for name in MapPublisherConfig.__dataclass_fields__},
                      ("map",), CONFIG / "planner.yaml", "map_publisher"),
}
UNSET = object()


def _literal(text: str):
    """A README default cell's leading value ("0.2, pause after ..." -> 0.2), or UNSET when it is prose."""
    text = text.strip().replace("`", "")
    text = re.split(r"[;:(]| \(|, [a-z]", text, maxsplit=1)[0].strip().rstrip(",")
    if text == '""':
        return ""
    if text.startswith("required"):
        return UNSET
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError:
        return UNSET
    if isinstance(value, str) and (" " in value or not value):
        return UNSET
    return value


def readme_section(readme: Path, heading: str) -> list:
    lines = readme.read_text().splitlines()
    start = next(k for k, line in enumerate(lines) if line == heading or line.startswith(heading + " "))
    level = len(heading.split()[0])
    section = []
    for line in lines[start + 1:]:
        if line.startswith("#") and len(line.split()[0]) <= level:
            break
        section.append(line)
    return section


def readme_defaults(readme: Path, heading: str) -> dict:
    defaults = {}
    for line in readme_section(readme, heading):
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if len(cells) < 3:
            continue
        if cells[0] == "parameter":          # | parameter | `~name` | type | default |
            names_cell, default_cell = cells[1], cells[3] if len(cells) > 3 else ""
        elif cells[0].startswith("`~"):      # | `~name` | type | default | meaning |
            names_cell, default_cell = cells[0], cells[2]
        else:
            continue
        names = re.findall(r"`~(\w+)`", names_cell)
        values = [default_cell] if len(names) == 1 else re.split(r",\s*", default_cell, maxsplit=len(names) - 1)
        for name, value in zip(names, values + values[-1:] * (len(names) - len(values))):   # "map centre": both
            defaults[name] = _literal(value)
    return defaults


def same(a, b) -> bool:
    if isinstance(a, bool) or isinstance(b, bool):
        return a is b
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return (math.isnan(a) and math.isnan(b)) or math.isclose(a, b, rel_tol=1e-12)
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    return a == b


@pytest.mark.parametrize("node", sorted(NODES))
def test_the_readme_table_is_the_dataclasses(node):
    """Every parameter the node reads is in its README table with its field's default, and the table lists
    no parameter the node does not read. Prose stands in for a value only where there is none (NaN: "the map
    centre"; a required parameter)."""
    readme, heading, node_defaults, required, _, _ = NODES[node]
    documented, defaults = readme_defaults(readme, heading), node_defaults()
    problems = [f"~{name}: read by the node, not in the README" for name in defaults if name not in documented]
    problems += [f"~{name}: in the README, not read by the node" for name in documented
                 if name not in defaults and name not in required]
    for name, default in defaults.items():
        value = documented.get(name, UNSET)
        if name not in documented or (value is UNSET and isinstance(default, float) and math.isnan(default)):
            continue
        if default is None and value == "":
            continue                                  # None: unset, as "" reads
        if value is UNSET or not same(value, default):
            problems.append(f"~{name}: README {'prose' if value is UNSET else repr(value)}, default {default!r}")
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize("node", sorted(NODES))
def test_the_yaml_file_holds_only_overrides(node):
    """A value in launch/config equal to its default would be a second copy of it."""
    _, _, node_defaults, _, path, section = NODES[node]
    data = yaml.safe_load(path.read_text()) or {}
    overrides = (data.get(section) or {}) if section else data
    defaults = node_defaults()
    problems = []
    for name, value in overrides.items():
        if name not in defaults:
            problems.append(f"{path.name}: {name} is no parameter of {node}")
        elif name in ("dqn", "deployed_dqn"):
            problems += [f"{path.name}: {name}.{field} restates DQNConfig's default" for field, v in value.items()
                         if same(v, params.field_default(DQNConfig, field))]
        elif same(value, defaults[name]):
            problems.append(f"{path.name}: {name}: {value!r} restates the default")
    assert not problems, "\n".join(problems)


def test_the_demo_overrides_what_it_says_it_does():
    """workload.yaml is the demo's own load (not the node's default), and the root README describes it."""
    workload = yaml.safe_load((CONFIG / "workload.yaml").read_text())
    assert workload and set(workload) <= set(tools.WORKLOAD_PARAMETERS)
    levels = ", ".join(f"{round(100 * level)}" for level in workload["levels"][:-1])
    text = " ".join((WORKSPACE / "README.md").read_text().split())
    assert f"every {workload['phase_s']:g} s ({levels} or {round(100 * workload['levels'][-1])} %" in text


def fallbacks(source: Path):
    """(line, parameter, fallback) of every `get_param(name, x)`, `param(name, x)` or `p(name, x)` call whose
    fallback x is a literal (None, an absent value, excepted)."""
    found = []
    for node in ast.walk(ast.parse(source.read_text())):
        if not (isinstance(node, ast.Call) and len(node.args) == 2):
            continue
        func = node.func
        if not ((isinstance(func, ast.Name) and func.id == "p")
                or (isinstance(func, ast.Attribute) and func.attr in ("get_param", "param"))):
            continue
        try:
            value = ast.literal_eval(node.args[1])
        except ValueError:
            continue
        if value is not None:
            found.append((node.lineno, ast.unparse(node.args[0]), value))
    return found


def test_no_python_node_restates_a_default():
    """A node's fallback is its dataclass field (`Config.name`) or the params helper's table, never a literal."""
    sources = [path for path in sorted((WORKSPACE / "src").rglob("*.py")) if "/test/" not in str(path)]
    found = [f"{path.relative_to(WORKSPACE)}:{line}: {name} falls back to {value!r}"
             for path in sources for line, name, value in fallbacks(path)]
    assert not found, "\n".join(found)


def test_the_restated_default_check_finds_one(tmp_path):
    source = tmp_path / "node.py"
    source.write_text('import rospy\nx = rospy.get_param("~probe_rate", 0.05)\ny = rospy.get_param("~a", A.b)\n')
    assert fallbacks(source) == [(2, "'~probe_rate'", 0.05)]


def launch_feeds(path: Path) -> dict:
    """launch argument -> [(node name, parameter)] it sets, through included launch files too."""
    feeds = {}
    root = ElementTree.parse(path).getroot()
    for node in root.iter("node"):
        for param in node.iter("param"):
            used = re.fullmatch(r"\$\(arg (\w+)\)", param.get("value", ""))
            if used:
                feeds.setdefault(used.group(1), []).append((node.get("name"), param.get("name")))
    for include in root.iter("include"):
        inner = launch_feeds(Path(include.get("file").replace("$(dirname)", str(path.parent))))
        for arg in include.iter("arg"):
            used = re.fullmatch(r"\$\(arg (\w+)\)", arg.get("value", ""))
            if used:
                feeds.setdefault(used.group(1), []).extend(inner.get(arg.get("name"), []))
    return feeds


# The demo's run seed and time origin: one value it hands to every process of a run, the WAN emulator's
# command line too (which cannot take it unset), not a node's default restated.
RUN_WIDE = {("offload_demo.launch", "seed"), ("offload_demo.launch", "epoch")}


@pytest.mark.parametrize("launch", ["robot.launch", "offload_demo.launch", "planner.launch"])
def test_launch_files_pass_arguments_through(launch):
    """An argument's default, or a literal <param>, equal to the default of a parameter it sets is a second
    copy of that default: arguments default to "" (set nothing) instead."""
    path = LAUNCH / launch
    root = ElementTree.parse(path).getroot()
    tables = {name: NODES[name][2]() for name in NODES}
    problems = []
    for arg in root.iter("arg"):
        default = arg.get("default")
        if default in (None, "") or "$(" in default or (launch, arg.get("name")) in RUN_WIDE:
            continue
        for node, name in launch_feeds(path).get(arg.get("name"), []):
            if name in tables.get(node, {}) and same(yaml.safe_load(default), tables[node][name]):
                problems.append(f"arg {arg.get('name')} = {default!r} restates {node}'s ~{name} default")
    for node in root.iter("node"):
        for param in node.iter("param"):
            value, name = param.get("value", ""), param.get("name")
            if "$(" not in value and name in tables.get(node.get("name"), {}) \
                    and same(yaml.safe_load(value), tables[node.get("name")][name]):
                problems.append(f"{node.get('name')}: ~{name} = {value!r} restates its default")
    assert not problems, "\n".join(problems)


def test_the_launch_check_follows_includes():
    feeds = launch_feeds(LAUNCH / "offload_demo.launch")
    assert ("offload_learner", "probe_rate") in feeds["probe_rate"]
    assert ("cloud_bridge", "timeout_s") in launch_feeds(LAUNCH / "robot.launch")["cloud_timeout_s"]


def test_settings_shared_by_two_configs_have_one_default():
    """robot.launch's cloud_timeout_s sets the bridge's deadline and the learner's l_cloud of a failure; ~seed
    seeds the session and the router's probe draws."""
    assert RouterConfig.cloud_timeout_s == BridgeConfig.timeout_s
    assert RouterConfig.seed == SessionConfig.seed


def dqn_pairs(text: str) -> dict:
    return {name: yaml.safe_load(value) for name, value in re.findall(r"`(\w+): ([\d.e+-]+)`", text)}


def test_the_readme_states_the_dqn_defaults_it_names():
    """The ~dqn row names DQNConfig's defaults; the offline choices name the experiments' schedule over them."""
    readme = (LEARNER / "README.md").read_text()
    row = next(line for line in readme.splitlines() if line.startswith("| `~dqn` |"))
    paragraph = next(line for line in readme.split("\n- ") if line.startswith("**Hyperparameters**"))
    for text, expected in ((row, DQNConfig().to_dict()), (paragraph, {**DQNConfig().to_dict(), **EXPERIMENT_SCHEDULE})):
        named = dqn_pairs(text)
        assert len(named) >= 4, text
        wrong = {name: value for name, value in named.items() if not same(value, expected[name])}
        assert not wrong, (wrong, expected)


def test_the_learner_readme_states_the_defaults_its_measurements_name():
    """The off-policy evaluation section names the deployed defaults it measured at."""
    text = " ".join((LEARNER / "README.md").read_text().split())
    probe_rate, epsilon = RouterConfig.probe_rate, DQNConfig.epsilon
    for phrase in (f"| {probe_rate:g}, {epsilon:g} (the deployed defaults) |",
                   f"the deployed probe rate {probe_rate:g}"):
        assert phrase in text, phrase


def test_the_root_readme_states_the_learners_defaults_it_names():
    """The root README's account of deployed mode and of the two guards names values: the learner's defaults."""
    text = " ".join((WORKSPACE / "README.md").read_text().split())
    router, breaker = RouterConfig(), RouterConfig().breaker
    for phrase in (f"{round(100 * router.probe_rate)} % of requests (`probe_rate`)",
                   f"the {round(100 * router.hedge_quantile)}th percentile of that side's latency model for the state, "
                   f"clamped to {router.hedge_min_s:g}-{router.hedge_max_s:g} s",
                   f"else at {router.hedge_max_s:g} s, so no request waits",
                   f"after {breaker.failures_to_open} cloud failures in a row",
                   f"slower than {breaker.max_round_trip_s:g} s", f"every {breaker.retry_after_s:g} s one request"):
        assert phrase in text, phrase


def test_the_cloud_and_the_goals_plan_as_the_planner_does():
    """The bridge's planner options and map bound, and the goal generator's free-cell rule, default to the
    planner node's (the core's options table; max_map_cells: planner_ros.cpp's)."""
    planner, bridge = planner_node_defaults(), bridge_defaults()
    shared = [name for name in planner if name in bridge and name != "planner_name"]   # each names itself
    assert len(shared) >= 10, shared
    assert {name: bridge[name] for name in shared} == {name: planner[name] for name in shared}
    assert BridgeConfig(endpoint="tcp://x:1").planner_parameters() == cloud_bridge.planner_defaults()
    goals = NODES["goal_generator"][2]()
    assert (goals["lethal_threshold"], goals["unknown_is_obstacle"]) == \
        (planner["lethal_threshold"], planner["unknown_is_obstacle"])


def test_the_checker_reads_every_source():
    """The parsers find what they must, so an empty parse cannot pass silently."""
    learner = NODES["offload_learner"]
    assert readme_defaults(*learner[:2])["probe_rate"] == RouterConfig.probe_rate
    assert learner[2]()["probe_rate"] == RouterConfig.probe_rate
    assert readme_defaults(*NODES["goal_generator"][:2])["tolerance"] == 0.0
    assert readme_defaults(*NODES["robot_workload"][:2])["levels"] == [0.0, 0.3, 0.55, 0.75]
    assert set(readme_defaults(*NODES["cloud_bridge"][:2])) >= set(cloud_bridge.PARAMETERS)
    assert cpp_node_defaults() == {"planner_name": "local", "max_map_cells": 64000000, "planning_threads": 4}
    assert {"lethal_threshold", "algorithm", "robot_radius"} <= set(cloud_bridge.planner_defaults())
