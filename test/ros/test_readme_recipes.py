"""The README's "Recipes and changeover" commands, verbatim, against the demo cell (its robot_cell
has two recipes; its simulated EMs take their time to change over; the gripper's
``wrong_fingers`` fault refuses the next recipe once)."""

from __future__ import annotations

from pathlib import Path

import pytest

from test.workspace.tools import (
    ROOT,
    Background,
    code_blocks,
    console_commands,
    shell,
    shown_in,
    wait_all_ems_online,
)

pytestmark = pytest.mark.ros


def recipe_block() -> list[tuple[str, list[str]]]:
    blocks = [console_commands(b) for b in code_blocks("console")]
    return next(b for b in blocks if any(c.startswith("packml recipe") for c, _ in b))


@pytest.mark.timeout(300)
def test_the_readme_changes_the_demo_robot_cell_over(tmp_path: Path) -> None:
    commands = recipe_block()
    assert [c for c, _ in commands] == [
        "packml recipe robot_cell",
        "packml recipe robot_cell --show 2",
        "packml fault robot_cell/gripper wrong_fingers on",
        "packml recipe robot_cell 2",
        "packml recipe robot_cell 2",
    ]
    here = tmp_path / "work"
    here.mkdir()
    (here / "config").symlink_to(ROOT / "config")
    cell = Background("packml launch config/demo_cell.yaml", tmp_path, here, tmp_path / "cell.log")
    try:
        cell.wait_for("is up", 120)
        wait_all_ems_online(tmp_path)
        codes = []
        outputs = []
        for command, shown in commands:
            got = shell(f"{command} --timeout 30", tmp_path, here, timeout=120)
            outputs.append(got.stdout)
            codes.append(got.returncode)
            assert shown_in(shown, got.stdout) is None, (command, got.stdout)
        # refused once (exit 1: the gripper's fault), then applied (exit 0)
        assert codes == [0, 0, 0, 1, 0], list(zip(codes, outputs, strict=True))
        assert "gripper: refused: the fingers for this part are not in the rack" in outputs[3]
        assert "recipe 2 'part B' applied in" in outputs[4]
        listed = shell("packml recipe robot_cell --timeout 30", tmp_path, here, timeout=60)
        assert "*    2  part B" in listed.stdout, listed.stdout
        assert cell.ctrl_c(60) == 0, cell.output()[-3000:]
    finally:
        cell.kill()
