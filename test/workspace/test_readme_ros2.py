"""Every ``ros2 ...`` command the README shows for the demo cell, run verbatim with the real ROS 2
command line (built from ../shared/vendor/ros2-tools by tools/setup.sh --test) against the demo
cell as ``make demo`` starts it, and its output compared with the one the README shows."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from .tools import (
    ROOT,
    Background,
    code_blocks,
    console_commands,
    ros2_daemon,
    shell,
    shown_in,
    wait_all_ems_online,
)

pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.timeout(300)]


def readme_ros2_commands() -> list[tuple[str, list[str]]]:
    commands = [
        (command, shown)
        for block in code_blocks("console")
        for command, shown in console_commands(block)
        if command.startswith("ros2 ")
    ]
    assert len(commands) >= 8, "the README's ros2 commands were not found"
    return commands


def test_the_readme_shows_a_refusal_a_latched_echo_an_interface_and_parameters() -> None:
    shown = " ".join(command for command, _ in readme_ros2_commands())
    for part in ("ros2 service call", "ros2 topic echo --once", "ros2 interface show",
                 "ros2 param get", "ros2 param set"):  # fmt: skip
        assert part in shown


def test_every_ros2_command_of_the_readme_against_the_demo_cell(tmp_path: Path) -> None:
    require_tools()
    cell = Background("packml launch config/demo_cell.yaml", tmp_path, ROOT, tmp_path / "cell.log")
    try:
        cell.wait_for("is up")
        wait_all_ems_online(tmp_path)
        with ros2_daemon(tmp_path):
            # A user's daemon has been running for a while and knows the graph (what `topic echo`
            # asks for the publishers' QoS, `param` for the node): start it, wait until it does.
            deadline = time.monotonic() + 60
            while True:
                nodes = shell("ros2 node list", tmp_path, ROOT)
                if nodes.stdout.count("/demo_cell/") >= 10 or time.monotonic() > deadline:
                    break
            for command, expected in readme_ros2_commands():
                # The graph is eventually consistent: a daemon busy past ros2cli's timeout makes
                # the command fall back to a node of its own that has not discovered the cell
                # yet (`ros2 node list` printed nothing once, right after listing all 13 nodes).
                # A command is run again until its output shows what the README shows, or 30 s.
                tried_until = time.monotonic() + 30
                while True:
                    result = shell(command, tmp_path, ROOT, timeout=60)
                    missing = shown_in(expected, result.stdout)
                    done = result.returncode == 0 and missing is None
                    if done or time.monotonic() > tried_until:
                        break
                assert result.returncode == 0, f"$ {command}\n{result.stdout}"
                assert missing is None, (
                    f"$ {command}\nthe README shows {missing!r}; the output was:\n{result.stdout}"
                )
        assert cell.ctrl_c() == 0, cell.output()[-3000:]
    finally:
        cell.kill()


def require_tools() -> None:
    from .tools import require

    require("ros2")
