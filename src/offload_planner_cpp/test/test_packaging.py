"""The pip-installed package (what a cloud host runs) declares every third-party module its shipped
modules import, lazy imports inside functions included, and ships no import of a module it leaves out."""
import ast
import fnmatch
import importlib.metadata
import re
import sys
import tomllib
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1]
SOURCE = PACKAGE / "src"


def pyproject():
    return tomllib.loads((PACKAGE / "pyproject.toml").read_text())


def normalized(distribution: str) -> str:
    return re.sub(r"[-_.]+", "-", distribution).lower()   # PEP 503


def package_modules():
    """Every .py file of the wheel packages as the wheel names it, and whether the wheel ships it
    (wheel.exclude drops the rospy nodes and the demo tools)."""
    config = pyproject()["tool"]["scikit-build"]
    excluded = config["wheel"]["exclude"]
    modules = {}
    for root in config["wheel"]["packages"]:
        root = PACKAGE / root
        for source in sorted(root.rglob("*.py")):
            inside = (Path(root.name) / source.relative_to(root)).as_posix()
            modules[inside] = (source, not any(fnmatch.fnmatch(inside, pattern) for pattern in excluded))
    return modules


def shipped_modules():
    return {inside: source for inside, (source, shipped) in package_modules().items() if shipped}


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


def declared_distributions():
    return {normalized(re.match(r"[A-Za-z0-9._-]+", requirement).group(0))
            for requirement in pyproject()["project"]["dependencies"]}


def test_the_wheel_ships_the_cloud_modules():
    shipped = shipped_modules()
    assert {"offload_planner_cpp/maps.py", "offload_planner_cpp/cloud/server.py",
            "offload_planner_cpp/cloud/client.py"} <= set(shipped)
    assert not [name for name in shipped if "/nodes/" in name or "/devtools/" in name]


def test_every_third_party_import_is_a_declared_dependency():
    providers = importlib.metadata.packages_distributions()
    declared = declared_distributions()
    left_out = {dotted(inside) for inside, (_, shipped) in package_modules().items() if not shipped}
    missing = []
    for inside, source in shipped_modules().items():
        names = set(imports(source, inside))
        for module in sorted(names):
            if any(module == out or module.startswith(out + ".") for out in left_out):
                missing.append(f"{inside} imports {module}, which the wheel leaves out")
        for top in sorted({module.split(".")[0] for module in names}):
            if top in sys.stdlib_module_names or top == "offload_planner_cpp":
                continue
            distributions = {normalized(d) for d in providers.get(top, [])}
            assert distributions, f"{inside} imports {top}, which no installed distribution provides"
            if not distributions & declared:
                missing.append(f"{inside} imports {top}: add {sorted(distributions)[0]} to [project] dependencies")
    assert not missing, "the pip-installed package would fail to import:\n" + "\n".join(missing)


def test_the_check_sees_lazy_imports_inside_functions():
    # maps.py imports yaml and PIL inside its loaders, which is how they went undeclared once.
    found = set(imports(SOURCE / "offload_planner_cpp" / "maps.py", "offload_planner_cpp/maps.py"))
    assert {"yaml", "PIL"} <= found
