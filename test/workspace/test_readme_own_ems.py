"""Issue 26: the README's "Your own equipment modules" walkthrough, run verbatim from a clone: its
EM file and cell file written as shown, its command lines run as shown (terminal 1 and terminal 2
in the background), the unit taken through reset, start, hold, unhold, stop and abort."""

from __future__ import annotations

from pathlib import Path

import pytest

from .tools import README, Background, code_blocks, shell

pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.timeout(300)]


def section() -> tuple[str, str, list[str]]:
    """The EM module, the cell file and the command lines of the walkthrough."""
    text = README.read_text(encoding="utf-8")
    assert "## Your own equipment modules" in text
    ems = next(b for b in code_blocks("python") if b.startswith('"""My cell\'s own EMs'))
    cell = next(b for b in code_blocks("yaml") if b.startswith("cell: my_cell"))
    lines = next(b for b in code_blocks("sh") if "packml launch cell.yaml --check" in b)
    return ems, cell, lines.splitlines()


def test_the_readme_walkthrough_of_own_ems(tmp_path: Path) -> None:
    ems, cell, lines = section()
    here = tmp_path / "my_cell"
    here.mkdir()
    (here / "my_ems.py").write_text(ems)
    (here / "cell.yaml").write_text(cell)
    check, launch_line, camera_line, *commands = lines
    assert "terminal 1" in launch_line and "terminal 2" in camera_line
    checked = shell(check, tmp_path, here)
    assert checked.returncode == 0, checked.stdout
    for em, how in (("press/feeder", "sim:"), ("press/gripper", "run: my_ems:Gripper"),
                    ("press/camera", "external:")):  # fmt: skip
        assert any(line.split()[:2] == [em, how.split()[0]] and how in line
                   for line in checked.stdout.splitlines()), checked.stdout  # fmt: skip
    launch = Background(launch_line, tmp_path, here, tmp_path / "launch.log")
    camera = None
    try:
        launch.wait_for("waiting for external EM(s) press/camera")
        camera = Background(camera_line, tmp_path, here, tmp_path / "camera.log")
        launch.wait_for("is up")
        states = {"reset": "IDLE", "start": "EXECUTE", "hold": "HELD", "unhold": "EXECUTE",
                  "stop": "STOPPED", "abort": "ABORTED"}  # fmt: skip
        assert [c.split()[3] for c in commands] == list(states)
        for line in commands:
            result = shell(line, tmp_path, here)
            assert result.returncode == 0, f"$ {line}\n{result.stdout}"
            assert f"now {states[line.split()[3]]}" in result.stdout, f"$ {line}\n{result.stdout}"
        assert camera.ctrl_c() == 0, camera.output()
        assert launch.ctrl_c() == 0, launch.output()[-3000:]
    finally:
        if camera is not None:
            camera.kill()
        launch.kill()
