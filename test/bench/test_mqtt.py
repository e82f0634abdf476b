"""bench/mqtt.py at its smallest: the JSON has the latency beside its floor and goal, and the rate
at rest (the figures themselves are the benchmark's, not asserted here)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
pytestmark = [pytest.mark.ros]


def test_mqtt_json_has_each_figure_beside_its_floor() -> None:
    out = subprocess.run([sys.executable, str(REPO / "bench/mqtt.py"), "--changes", "6", "--rest", "1"],
                         capture_output=True, text=True, timeout=110, check=False)  # fmt: skip
    assert out.returncode == 0, out.stderr[-3000:]
    got = json.loads(out.stdout)
    assert got["changes"] == 6 and got["goal_ratio"] == 1.5
    for key in ("status_to_ddata_ms", "floor_bare_publish_ms", "unit_to_ddata_ms"):
        assert set(got[key]) == {"p50", "p99", "max"} and got[key]["p50"] > 0, (key, got)
    ratio = got["status_to_ddata_ms"]["p50"] / got["floor_bare_publish_ms"]["p50"]
    assert abs(got["ratio_p50"] - ratio) <= 0.02 * ratio + 0.01, got  # fmt: skip
    assert got["messages_per_s_per_unit_at_rest"] >= 0 and got["rest_window_s"] == 1
