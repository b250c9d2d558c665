"""The pip-installed packages (what a cloud host runs: the planner's wheel and the cloud package's) declare
every third-party module their shipped modules import, lazy imports inside functions included, and ship no
import of a module they leave out."""
import ast
import fnmatch
import importlib.metadata
import re
import sys
import tomllib
from pathlib import Path

import pytest

WORKSPACE = Path(__file__).resolve().parents[1]
PLANNER = WORKSPACE / "src" / "offload_planner_cpp"
CLOUD = WORKSPACE / "src" / "offload_cloud"
WHEELS = {"offload_planner_cpp": PLANNER, "offload_cloud": CLOUD}


def pyproject(package):
    return tomllib.loads((package / "pyproject.toml").read_text())


def normalized(distribution: str) -> str:
    return re.sub(r"[-_.]+", "-", distribution).lower()   # PEP 503


def wheel_config(package):
    """(package roots, excluded patterns) of the wheel: scikit-build-core's (the planner) or hatchling's."""
    tool = pyproject(package)["tool"]
    if "scikit-build" in tool:
        wheel = tool["scikit-build"]["wheel"]
        return wheel["packages"], wheel.get("exclude", [])
    wheel = tool["hatch"]["build"]["targets"]["wheel"]
    return wheel["packages"], wheel.get("exclude", [])


def package_modules(package):
    """Every .py file of the wheel packages as the wheel names it, and whether the wheel ships it
    (the planner's wheel.exclude drops its rospy node)."""
    roots, excluded = wheel_config(package)
    modules = {}
    for root in roots:
        root = package / root
        for source in sorted(root.rglob("*.py")):
            inside = (Path(root.name) / source.relative_to(root)).as_posix()
            modules[inside] = (source, not any(fnmatch.fnmatch(inside, pattern) for pattern in excluded))
    return modules


def shipped_modules(package):
    return {inside: source for inside, (source, shipped) in package_modules(package).items() if shipped}


def dotted(inside: str) -> str:
    return inside[:-len(".py")].replace("/", ".").removesuffix(".__init__")


def imports(source: Path, inside: str):
    """Absolute names of every module `source` imports (for `from A import b`, both A and A.b, as b may be
    a module), relative imports resolved against `inside`."""
    package = dotted(inside) if inside.endswith("__init__.py") else dotted(inside).rsplit(".", 1)[0]
    for node in ast.walk(ast.parse(source.read_text())):
        if isinstance(node, ast.Import):
            yield from (alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level == 0:
                base = node.module
            else:
                base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                base = f"{base}.{node.module}" if node.module else base
            yield base
            yield from (f"{base}.{alias.name}" for alias in node.names if alias.name != "*")


# Optional parts of a wheel: modules under the folder need only the extra's distributions beyond the core ones
# (the cloud package's fleet learner, `pip install 'offload-cloud[learner]'`).
EXTRAS = {"offload_cloud": {"offload_cloud/learner/": "learner"}}
# The workspace's packages that are installed from source beside the wheels, not from an index.
FROM_SOURCE = {"offload_learner_py"}


def _names(requirements):
    return {normalized(re.match(r"[A-Za-z0-9._-]+", requirement).group(0)) for requirement in requirements}


def declared_distributions(package, inside: str = ""):
    """The distributions the wheel declares for the module `inside`: the core dependencies, plus an extra's when
    the module belongs to an optional part."""
    project = pyproject(package)["project"]
    declared = _names(project["dependencies"])
    for folder, extra in EXTRAS.get(package.name, {}).items():
        if inside.startswith(folder):
            declared |= _names(project["optional-dependencies"][extra])
    return declared


def test_the_planner_wheel_is_the_planner_alone():
    shipped = set(shipped_modules(PLANNER))
    assert shipped == {"offload_planner_cpp/__init__.py", "offload_planner_cpp/maps.py"}, shipped
    assert "offload_planner_cpp/nodes/map_publisher.py" in package_modules(PLANNER)   # there, left out


def test_the_cloud_wheel_ships_the_server_and_the_client():
    shipped = set(shipped_modules(CLOUD))
    assert {"offload_cloud/server.py", "offload_cloud/client.py", "offload_cloud/protocol.py"} <= shipped
    assert "offload-planner-cpp" in declared_distributions(CLOUD)


@pytest.mark.parametrize("top", sorted(WHEELS))
def test_every_third_party_import_is_a_declared_dependency(top):
    package = WHEELS[top]
    providers = importlib.metadata.packages_distributions()
    left_out = {dotted(inside) for inside, (_, shipped) in package_modules(package).items() if not shipped}
    missing = []
    for inside, source in shipped_modules(package).items():
        names = set(imports(source, inside))
        declared = declared_distributions(package, inside)
        for module in sorted(names):
            if any(module == out or module.startswith(out + ".") for out in left_out):
                missing.append(f"{inside} imports {module}, which the wheel leaves out")
        for imported in sorted({module.split(".")[0] for module in names}):
            if imported in sys.stdlib_module_names or imported == top:
                continue
            if imported in WHEELS or imported in FROM_SOURCE:   # the workspace's own packages, from source
                if normalized(imported) not in declared:
                    missing.append(f"{inside} imports {imported}: add {normalized(imported)} to [project] dependencies")
                continue
            distributions = {normalized(d) for d in providers.get(imported, [])}
            assert distributions, f"{inside} imports {imported}, which no installed distribution provides"
            if not distributions & declared:
                missing.append(f"{inside} imports {imported}: add {sorted(distributions)[0]} to [project] dependencies")
    assert not missing, "the pip-installed package would fail to import:\n" + "\n".join(missing)


def test_the_check_sees_lazy_imports_inside_functions():
    # maps.py imports yaml and PIL inside its loaders, which is how they went undeclared once.
    found = set(imports(PLANNER / "src" / "offload_planner_cpp" / "maps.py", "offload_planner_cpp/maps.py"))
    assert {"yaml", "PIL"} <= found


def test_the_learner_extra_is_declared_and_only_the_learner_uses_it():
    """The fleet learner's torch, rosbags and offload_learner_py are the `learner` extra's, and no module outside
    offload_cloud/learner/ imports them or the learner: the planner server and the client library stay without
    torch."""
    extra = _names(pyproject(CLOUD)["project"]["optional-dependencies"]["learner"])
    assert {"torch", "rosbags", "offload-learner-py"} <= extra
    assert not extra & declared_distributions(CLOUD)
    assert pyproject(CLOUD)["project"]["scripts"]["offload-cloud-learner"] == "offload_cloud.learner.cli:main"
    for inside, source in shipped_modules(CLOUD).items():
        if inside.startswith("offload_cloud/learner/"):
            continue
        heavy = {m for m in imports(source, inside)
                 if m.split(".")[0] in ("torch", "rosbags", "offload_learner_py") or m.startswith("offload_cloud.learner")}
        assert not heavy, f"{inside} imports {sorted(heavy)}: only offload_cloud/learner/ may"


def test_the_extra_check_sees_an_undeclared_learner_import():
    assert "torch" not in declared_distributions(CLOUD, "offload_cloud/server.py")
    assert "torch" in declared_distributions(CLOUD, "offload_cloud/learner/training.py")
