"""cfg/Planner.cfg as generated for Python (the cloud bridge node reads its updates): every parameter a node parameter
of the core's options table with the table's default, the algorithm choices the core's names, and no bounds of its
own, so dynamic_reconfigure clamps nothing and the table refuses what it refuses (test_planner_reconfigure.cpp checks
the C++ side)."""
import ast
import math

import pytest

from offload_planner_cpp import ALGORITHM_NAMES, options_table


def test_the_generated_config_is_the_tables_node_parameters_unbounded():
    generated = pytest.importorskip("offload_planner_cpp.cfg.PlannerConfig", reason="built by catkin")
    rows = {row["name"]: row for row in options_table()}
    assert list(generated.defaults) == ["algorithm", "any_angle", "cost_factor", "robot_radius", "inflation_radius",
                                        "cost_scaling_factor"]
    for name, default in generated.defaults.items():
        assert rows[name]["node_parameter"], name
        assert default == rows[name]["default"], name
        assert generated.min[name] in (-math.inf, "", False) and generated.max[name] in (math.inf, "", True), name
    algorithm = next(p for p in generated.config_description["parameters"] if p["name"] == "algorithm")
    assert tuple(const["value"] for const in ast.literal_eval(algorithm["edit_method"])["enum"]) == ALGORITHM_NAMES
