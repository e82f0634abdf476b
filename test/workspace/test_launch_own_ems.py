"""Issue 26 under ``ros2 launch``: the cell of a simulated EM, a Python EM from ``run:``, an action
server's EM and an external EM started by hand (test/ros/test_own_ems.py) resets, starts, holds,
stops and aborts."""

from __future__ import annotations

import os
import re
import shlex
import time
from pathlib import Path

import pytest

from test.ros.test_own_ems import (
    WITH_ACTION,
    Camera,
    Servers,
    env_for,
    packml,
    run_through_the_states,
    write_cell,
)

from .tools import ROOT, Background, require

pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.timeout(300)]


def wait_online(tmp_path: Path, cell: str, count: str, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while True:
        status = packml(tmp_path, "status", "--cell", cell)
        if re.search(rf"press .* {count} ", status.stdout):
            return
        assert time.monotonic() < deadline, status.stdout + status.stderr


def test_ros2_launch_of_a_cell_with_sim_run_and_external_ems(tmp_path: Path) -> None:
    require("ros2")
    cell = f"rl{os.getpid()}"
    path = write_cell(tmp_path, cell, WITH_ACTION)
    servers = Servers(tmp_path, cell)  # the robot's drivers the action EM uses
    env = env_for(tmp_path)
    line = (f"PYTHONPATH={shlex.quote(env['PYTHONPATH'])} EMS_TRACE={shlex.quote(env['EMS_TRACE'])} "
            f"ros2 launch packml_ros2 cell.launch.py cell_file:={shlex.quote(str(path))}")  # fmt: skip
    launch = Background(line, tmp_path, ROOT, tmp_path / "launch.log")
    camera = None
    try:
        wait_online(tmp_path, cell, "3/4")  # feeder, gripper, mover; the camera is external
        camera = Camera(tmp_path, cell)
        wait_online(tmp_path, cell, "4/4")
        run_through_the_states(tmp_path)
        assert servers.output().count("goal 2 succeeded") >= 3, servers.output()
        assert launch.ctrl_c() == 0, launch.output()[-3000:]
        # the unit, the feeder, the gripper, the mover, the coordinator; nothing for the camera
        assert launch.after_ctrl_c().count("process has finished cleanly") == 5, launch.output()
    finally:
        if camera is not None:
            camera.stop()
        servers.stop()
        launch.kill()
