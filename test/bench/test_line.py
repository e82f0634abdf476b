"""bench/line.py at its smallest: two cells, one measured cycle. The JSON has the line's reset and
start beside the floor of the same calls by a bare client, the ratios computed from them, and the
benchmark leaves no process behind (the figures themselves are the benchmark's, not asserted)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
pytestmark = [pytest.mark.ros]


def test_line_json_has_each_figure_beside_its_floor(tmp_path: Path) -> None:
    out = subprocess.run([sys.executable, str(REPO / "bench/line.py"), "--cells", "2", "--cycles", "1",
                          "--publishing-interval", "0.02", "--keep", str(tmp_path)],
                         capture_output=True, text=True, timeout=300, check=False)  # fmt: skip
    assert out.returncode == 0, out.stderr[-3000:]
    got = json.loads(out.stdout)
    assert (got["cells"], got["cycles"], got["publishing_interval_s"]) == (2, 1, 0.02)
    for way in ("line", "floor"):
        for verb in ("reset", "start"):
            figure = got[f"{way}_{verb}"]
            assert figure["n"] == 1 and figure["p50_ms"] > 0 and len(figure["samples_ms"]) == 1
    for verb in ("reset", "start"):
        ratio = got[f"line_{verb}"]["p50_ms"] / got[f"floor_{verb}"]["p50_ms"]
        assert abs(got[f"{verb}_p50_over_floor"] - ratio) <= 0.01, got
    assert got["goal_met"] == (
        got["start_p50_over_floor"] <= got["goal_start_p50_over_floor"] == 1.5
    )
    # each cell and the line were launched by `packml launch` and ended with the benchmark
    logs = sorted(p.name for p in tmp_path.glob("*.log"))
    assert len(logs) == 3 and "line.log" in logs
    leftover = subprocess.run(
        ["pgrep", "-f", str(tmp_path)], capture_output=True, text=True, check=False
    )
    assert leftover.stdout.strip() == "", leftover.stdout
