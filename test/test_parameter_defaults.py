"""Each node parameter's default is one value: the node's own fallback in code, the YAML file its launch
files load, and the package README's parameter table say the same thing. A default changed in one place
only fails here."""
import ast
import math
import re
from pathlib import Path

import pytest
import yaml

WORKSPACE = Path(__file__).resolve().parents[1]
LEARNER = WORKSPACE / "src" / "offload_learner_py"
PLANNER = WORKSPACE / "src" / "offload_planner_cpp"
DEMOS = WORKSPACE / "src" / "offload_demos"
CONFIG = WORKSPACE / "launch" / "config"

# node: (README, its section heading, the code that reads the parameters, YAML file, section in it)
NODES = {
    "offload_learner": (LEARNER / "README.md", "### offload_learner",
                        LEARNER / "src/offload_learner_py/nodes/learner.py", CONFIG / "learner.yaml", None),
    "goal_generator": (DEMOS / "README.md", "### goal_generator",
                       DEMOS / "src/offload_demos/goal_generator.py", CONFIG / "goal_generator.yaml", None),
    "planner": (PLANNER / "README.md", "### planner_node", PLANNER / "src/planner_ros.cpp",
                CONFIG / "planner.yaml", "planner"),
    "map_publisher": (PLANNER / "README.md", "### map_publisher",
                      PLANNER / "src/offload_planner_cpp/nodes/map_publisher.py", CONFIG / "planner.yaml",
                      "map_publisher"),
    "cloud_bridge": (LEARNER / "README.md", "### cloud_bridge",
                     LEARNER / "src/offload_learner_py/nodes/cloud_bridge.py", CONFIG / "cloud_bridge.yaml",
                     "cloud_bridge"),
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


def readme_defaults(readme: Path, heading: str) -> dict:
    lines = readme.read_text().splitlines()
    start = next(k for k, line in enumerate(lines) if line == heading or line.startswith(heading + " "))
    level = len(heading.split()[0])
    section = []
    for line in lines[start + 1:]:
        if line.startswith("#") and len(line.split()[0]) <= level:
            break
        section.append(line)
    defaults = {}
    for line in section:
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
        for name, value in zip(names, values + [""] * (len(names) - len(values))):
            defaults[name] = _literal(value)
    return defaults


def code_defaults(source: Path) -> dict:
    """name -> literal fallback of every `p("name", x)` / `rospy.get_param("~name", x)` (Python) or
    `param("name", var, x)` (roscpp) with a literal x."""
    text = source.read_text()
    found = {}
    if source.suffix == ".cpp":
        for name, value in re.findall(r'param\(\s*"(\w+)"\s*,\s*[\w.]+\s*,\s*([^)]+)\)', text):
            if re.fullmatch(r'-?[\d.]+|true|false|".*"', value.strip()):   # a literal, not a struct's default
                found[name] = yaml.safe_load(value.strip())
        return found
    for node in ast.walk(ast.parse(text)):
        if not (isinstance(node, ast.Call) and len(node.args) == 2 and isinstance(node.args[0], ast.Constant)
                and isinstance(node.args[0].value, str)):
            continue
        func = node.func
        if not ((isinstance(func, ast.Name) and func.id == "p")
                or (isinstance(func, ast.Attribute) and func.attr == "get_param")):
            continue
        try:
            found[node.args[0].value.lstrip("~")] = ast.literal_eval(node.args[1])
        except ValueError:
            pass
    return found


def yaml_values(path: Path, section) -> dict:
    data = yaml.safe_load(path.read_text())
    return data[section] if section else data


def same(a, b) -> bool:
    if isinstance(a, bool) or isinstance(b, bool):
        return a is b
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return math.isclose(a, b, rel_tol=1e-12)
    return a == b


@pytest.mark.parametrize("node", sorted(NODES))
def test_code_readme_and_yaml_defaults_agree(node):
    readme, heading, source, yaml_path, section = NODES[node]
    documented = readme_defaults(readme, heading)
    code = code_defaults(source)
    configured = yaml_values(yaml_path, section)
    assert documented and code, (documented, code)
    problems = []
    for name, value in configured.items():
        if name not in documented:
            problems.append(f"{yaml_path.name}: {name} is not in the README's table")
        elif isinstance(value, dict):
            continue                              # ~dqn: checked below
        elif documented[name] is not UNSET and not same(documented[name], value):
            problems.append(f"{name}: README {documented[name]!r}, {yaml_path.name} {value!r}")
        if name in code and not isinstance(value, dict) and not same(code[name], value):
            problems.append(f"{name}: code {code[name]!r}, {yaml_path.name} {value!r}")
    for name, value in documented.items():
        if value is not UNSET and name in code and not same(code[name], value):
            problems.append(f"{name}: code {code[name]!r}, README {value!r}")
    assert not problems, "\n".join(problems)


def test_the_learners_dqn_settings_are_documented_as_shipped():
    """learner.yaml's ~dqn block overrides DQNConfig's offline defaults for online use; the README states
    each value it ships."""
    readme, heading = NODES["offload_learner"][:2]
    row = next(line for line in readme.read_text().splitlines() if line.startswith("| `~dqn` |"))
    for name, value in yaml_values(CONFIG / "learner.yaml", None)["dqn"].items():
        assert f"{name}: {value}" in row, (name, value, row)
    row = next(line for line in readme.read_text().splitlines() if line.startswith("| `~deployed_dqn` |"))
    for name, value in yaml_values(CONFIG / "learner.yaml", None)["deployed_dqn"].items():
        assert f"{name}: {value}" in row, (name, value, row)


def test_the_checker_reads_all_three_sources():
    """The parsers find what they must, so an empty parse cannot pass the agreement test silently."""
    learner = NODES["offload_learner"]
    assert readme_defaults(*learner[:2])["probe_rate"] == 0.05
    assert code_defaults(learner[2])["probe_rate"] == 0.05
    assert code_defaults(NODES["planner"][2])["max_map_cells"] == 64000000
    assert readme_defaults(*NODES["goal_generator"][:2])["tolerance"] == 0.0
