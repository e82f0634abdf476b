"""The README's workspace lines, verbatim, with colcon from PyPI and the venv as the underlay:
both packages build (packml_interfaces lies inside packml_ros2, where colcon does not look by
itself); then, from the install space, ``ros2 run packml_ros2 unit_node ...`` answers a service
call and exits 0 on Ctrl-C, and ``ros2 launch packml_ros2 cell.launch.py ...`` runs the demo cell
through a reset/start and a clean Ctrl-C. The clone is of this repository's HEAD (committed
work)."""

from __future__ import annotations

import shlex
import subprocess
from pathlib import Path

import pytest

from .test_launch import run_the_demo_cell_and_ctrl_c
from .tools import ROOT, Background, code_blocks, require, shell

pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.timeout(900)]


def workspace_lines() -> list[str]:
    blocks = [b for b in code_blocks("sh") if "colcon build" in b]
    assert len(blocks) == 1, "the README's workspace block was not found"
    return [line for line in blocks[0].splitlines() if line.strip()]


def descendants(pid: int) -> list[str]:
    """Command lines of every process below ``pid``."""
    out = []
    children = subprocess.run(["pgrep", "-P", str(pid)], capture_output=True, text=True,
                              check=False).stdout.split()  # fmt: skip
    for child in children:
        cmdline = Path(f"/proc/{child}/cmdline")
        if cmdline.exists():
            out.append(cmdline.read_bytes().replace(b"\0", b" ").decode(errors="replace"))
        out += descendants(int(child))
    return out


def test_readme_workspace_builds_both_packages_and_runs_from_the_install_space(
    tmp_path: Path,
) -> None:
    require("ros2", "colcon")
    lines = workspace_lines()
    build = [line for line in lines if not line.startswith("ros2 ")]
    run, launch = (line for line in lines if line.startswith("ros2 "))
    assert run.startswith("ros2 run packml_ros2 unit_node ")
    assert launch.startswith("ros2 launch packml_ros2 cell.launch.py ")
    script = "\n".join(build).replace("<this repository>", shlex.quote(str(ROOT)))
    built = shell(script, tmp_path, tmp_path, timeout=1200)
    assert built.returncode == 0, built.stdout[-4000:]
    assert "Summary: 2 packages finished" in built.stdout, built.stdout[-4000:]
    ws = tmp_path / "ws"
    assert (ws / "install/packml_interfaces/share/packml_interfaces/package.xml").is_file()
    assert (ws / "install/packml_ros2/lib/packml_ros2/unit_node").is_file()

    in_ws = "cd ~/ws\n. install/setup.bash\n"  # the README's lines before `ros2 run`
    unit = Background(in_ws + f"exec {run}", tmp_path, tmp_path, tmp_path / "run.log")
    try:
        unit.wait_for("PackML unit /demo_cell/robot_cell up")
        assert any(
            "/ws/install/packml_ros2/lib/packml_ros2/unit_node" in c
            for c in descendants(unit.proc.pid)
        ), descendants(unit.proc.pid)
        answer = shell(in_ws + "ros2 service call /demo_cell/robot_cell/start std_srvs/srv/Trigger",
                       tmp_path, tmp_path, timeout=60)  # fmt: skip
        assert "START not allowed in STOPPED" in answer.stdout, answer.stdout
        assert unit.ctrl_c() == 0, unit.output()
        assert "shut down (SIGINT) in STOPPED" in unit.after_ctrl_c(), unit.output()
    finally:
        unit.kill()

    cell = Background(in_ws + launch, tmp_path, tmp_path, tmp_path / "launch.log")
    try:
        cell.wait_for("process started", 60)
        assert any(
            "/ws/install/packml_ros2/lib/packml_ros2/" in c for c in descendants(cell.proc.pid)
        )
        run_the_demo_cell_and_ctrl_c(cell, tmp_path)
    finally:
        cell.kill()
