"""The ROS 2 launch file starts the same nodes as `packml launch --processes`."""

from __future__ import annotations

import ast
import importlib.util
import sys
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


def test_ems_naming_one_process_share_it_and_programs_run_alone(tmp_path: Path) -> None:
    """Issue 26: EM classes with one ``process:`` are one em_node (across units too); a program
    EM is its own command, with its placeholders and environment."""
    path = tmp_path / "c.yaml"
    path.write_text(
        "cell: c\nunits:\n"
        "  a:\n    equipment_modules:\n"
        "      arm: {sim: {}, process: ctl}\n      wrist: {sim: {}, process: ctl}\n"
        "      belt: {sim: {}}\n"
        f"      cam: {{run: [{sys.executable}, -c, pass, '{{cell}}/{{unit}}/{{em}}']}}\n"
        "      remote: {external: true}\n"
        "  b:\n    equipment_modules:\n      tool: {sim: {}, process: ctl}\n"
    )
    specs = {s.name: s for s in node_specs(plan(path))}
    ctl = specs["em a/arm a/wrist b/tool"]
    assert (ctl.executable, ctl.arguments) == (
        "em_node",
        (str(path), "a", "arm", "wrist", "b/tool"),
    )
    assert specs["em a/belt"].arguments == (str(path), "a", "belt")
    cam = specs["em a/cam"]
    assert cam.executable == "" and cam.argv == (sys.executable, "-c", "pass", "c/a/cam")
    assert dict(cam.env)["PACKML_EM"] == "cam" and dict(cam.env)["PACKML_UNIT"] == "a"
    assert not any("remote" in name for name in specs)  # external: not started here
    dry = {s.name: s for s in node_specs(plan(path, simulate=True))}
    assert dry["em a/cam"].arguments[:2] == ("--sim", str(path))
