"""The README's "Certify a machine" commands, verbatim, against the demo cell (its units have
simulated EMs that take their time and count: the run with EMs)."""

from __future__ import annotations

import json
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


def conform_blocks() -> list[list[tuple[str, list[str]]]]:
    blocks = [console_commands(b) for b in code_blocks("console")]
    start = next(i for i, b in enumerate(blocks) if any("conform" in c for c, _ in b))
    return blocks[start : start + 2]


@pytest.mark.timeout(480)
def test_the_readme_certifies_the_demo_robot_cell(tmp_path: Path) -> None:
    (launch, _), (dry, planned) = conform_blocks()[0]
    [(run, reported)] = conform_blocks()[1]
    assert launch == "packml launch config/demo_cell.yaml" and dry.endswith("--dry"), launch
    here = (
        tmp_path / "work"
    )  # the reader's directory: config/ as in a clone, conform.xml lands here
    here.mkdir()
    (here / "config").symlink_to(ROOT / "config")
    cell = Background(launch, tmp_path, here, tmp_path / "cell.log")
    try:
        cell.wait_for("is up", 120)
        wait_all_ems_online(tmp_path)
        shown = shell(dry, tmp_path, here, timeout=60)
        assert shown.returncode == 0 and shown_in(planned, shown.stdout) is None, shown.stdout
        got = shell(run, tmp_path, here, timeout=400)
        assert got.returncode == 0, got.stdout[-5000:]
        assert shown_in(reported, got.stdout) is None, got.stdout[-5000:]
        # the JUnit file it wrote (in the directory the README runs it from), and the counters of
        # a unit whose EMs count: reset, AccCount kept
        junit = here / "conform.xml"
        assert junit.is_file() and 'failures="0"' in junit.read_text()
        counts = shell(
            "packml conform /demo_cell/robot_cell --yes --profile packtags --format json",
            tmp_path,
            ROOT,
            timeout=200,
        )
        assert counts.returncode == 0, counts.stdout[-3000:]
        doc = json.loads(counts.stdout[counts.stdout.index("{") :])
        reset = {r["check"]: r["message"] for r in doc["results"]}["counters-reset"]
        assert "AccCount kept" in reset and "not proven" not in reset, reset
        assert cell.ctrl_c(60) == 0, cell.output()[-3000:]
    finally:
        cell.kill()
