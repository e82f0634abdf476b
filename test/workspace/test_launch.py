"""``ros2 launch packml_ros2 cell.launch.py cell_file:=...`` with the real launch and launch_ros,
from make demo's venv (an ament prefix) as the README shows it: the demo cell comes up, a reset
and start go through, Ctrl-C (SIGINT to every process at once, as a terminal sends it) ends every
process with exit code 0 and prints only goodbye lines, and the saved admin data holds no fault
from the shutdown (the issue: "EM outfeed lost" became the StopReason, 3 runs of 3)."""

from __future__ import annotations

import re
import time
from pathlib import Path

import pytest

from test.ros.cells import saved_admin, saved_faults, shutdown_noise

from .tools import README, ROOT, Background, packml, require, wait_all_ems_online

pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.timeout(300)]
UNITS = ("robot_cell", "case_packer")


def readme_launch_line() -> str:
    found = re.search(r"`(ros2 launch packml_ros2 cell\.launch\.py cell_file:=config/\S+)`",
                      README.read_text(encoding="utf-8"))  # fmt: skip
    assert found, "the README's ros2 launch line for the checkout was not found"
    return found.group(1)


def run_the_demo_cell_and_ctrl_c(launch: Background, home: Path) -> str:
    """Reset and start the demo cell, Ctrl-C in Execute; returns what the terminal showed after."""
    wait_all_ems_online(home)
    for command in ("reset", "start"):
        result = packml("cmd", "demo_cell", command, home=home)
        assert result.returncode == 0, result.stdout + result.stderr
    assert "EXECUTE" in packml("status", home=home).stdout
    ctrl_c_at = time.time()
    assert launch.ctrl_c() == 0, launch.output()[-3000:]
    after = launch.after_ctrl_c()
    assert not shutdown_noise(after), after
    assert after.count("process has finished cleanly") == 10, after  # 2 units, 7 EMs, coordinator
    for unit in UNITS:
        saved = saved_admin(home / ".local/state/packml_ros2/demo_cell" / f"{unit}.sqlite3", unit)
        assert not saved_faults(saved, ctrl_c_at), (unit, saved_faults(saved, ctrl_c_at), after)
        assert saved["stop_reason"]["message"] == "unit shut down (SIGINT) in EXECUTE", saved
    return after


def test_ros2_launch_from_the_venv_and_ctrl_c_without_a_fault(tmp_path: Path) -> None:
    require("ros2")
    launch = Background(readme_launch_line(), tmp_path, ROOT, tmp_path / "launch.log")
    try:
        run_the_demo_cell_and_ctrl_c(launch, tmp_path)
    finally:
        launch.kill()
