"""The ROS 2 launch file starts the same nodes as `packml launch --processes`."""

from __future__ import annotations

import ast
import importlib.util
from pathlib import Path

import pytest

from packml_ros2.launcher import commands, node_specs, plan

ROOT = Path(__file__).resolve().parents[1]


def test_node_specs_of_the_demo_cell() -> None:
    specs = node_specs(plan(ROOT / "config" / "demo_cell.yaml"))
    assert [s.executable for s in specs].count("unit_node") == 2
    assert [s.executable for s in specs].count("em_node") == 7
    assert specs[-1].executable == "coordinator"
    assert ("robot_cell", "gripper") in {
        tuple(s.arguments[1:]) for s in specs if s.executable == "em_node"
    }
    # --processes runs exactly these, as modules of this interpreter
    assert [argv[2] for _, argv in commands(plan(ROOT / "config" / "demo_cell.yaml"))] == [
        s.module for s in specs
    ]


def test_every_executable_is_an_entry_point() -> None:
    setup = (ROOT / "setup.py").read_text()
    for spec in node_specs(plan(ROOT / "config" / "demo_cell.yaml")):
        assert f'"{spec.executable} = {spec.module}:main"' in setup or (
            spec.executable == "em_node" and '"em_node = packml_ros2.sim_em:main"' in setup
        )


def test_the_launch_file_is_valid_python_declaring_cell_file() -> None:
    source = (ROOT / "launch" / "cell.launch.py").read_text()
    tree = ast.parse(source)
    assert any(
        isinstance(n, ast.FunctionDef) and n.name == "generate_launch_description"
        for n in tree.body
    )
    assert '"cell_file"' in source


@pytest.mark.skipif(
    importlib.util.find_spec("launch_ros") is None,
    reason="launch_ros is not installed (no ROS 2 installation; not on PyPI)",
)
def test_the_launch_file_builds_its_nodes() -> (
    None
):  # pragma: no cover - needs a ROS 2 installation
    from launch import LaunchContext
    from launch.launch_description_sources import PythonLaunchDescriptionSource

    source = PythonLaunchDescriptionSource(str(ROOT / "launch" / "cell.launch.py"))
    description = source.get_launch_description(LaunchContext())
    assert description.entities
