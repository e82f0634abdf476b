"""bench/plant.py at its smallest: two cells on two "hosts" (network namespaces), simple
discovery. The JSON has every figure of each setup with the goals beside them, and the benchmark
leaves no namespace behind, also when it is interrupted. Skipped (with the reason) where network
namespaces cannot be created."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from packml_ros2.testing.netns import ip, why_no_namespaces

REPO = Path(__file__).resolve().parents[2]
PLANT = [sys.executable, str(REPO / "bench/plant.py")]

pytestmark = [pytest.mark.netns, pytest.mark.ros, pytest.mark.slow]


@pytest.fixture(autouse=True)
def _namespaces() -> None:
    reason = why_no_namespaces()
    if reason:
        pytest.skip(reason)


def namespaces_of(pid: int) -> list[str]:
    """The network namespaces bench/plant.py run as ``pid`` holds (named pl<pid>...)."""
    names = [line.split()[0] for line in ip("netns", "list").stdout.splitlines() if line.strip()]
    return [n for n in names if n.startswith(f"pl{pid % 100000}")]


def test_plant_json_has_every_figure_beside_its_goal(tmp_path: Path) -> None:
    kept = tmp_path / "kept"
    proc = subprocess.Popen(
        [*PLANT, "--cells", "2", "--hosts", "2", "--window", "3", "--rest", "3", "--idle", "2", "--cycles", "2",
         "--lease", "2", "--setups", "simple", "--em-lease", "3", "--keep", str(kept)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
    )  # fmt: skip
    out, err = proc.communicate(timeout=100)
    assert proc.returncode == 0, err[-3000:]
    result = json.loads(out)
    assert (result["cells"], result["hosts"], result["nodes"]) == (2, 2, 18)
    assert len(result["load_average_at_start"]) == len(result["load_average_at_end"]) == 3
    assert list(result["setups"]) == ["simple"]
    s = result["setups"]["simple"]
    assert 0 < s["ready_spread_s"]["first"] <= s["ready_spread_s"]["median"] <= s["ready_s"] < 60
    first = s["traffic_first_window"]
    assert first["seconds"] >= 3 and first["sent_bytes"] > 0 and first["sent_packets"] > 0
    assert set(first["per_host"]) == {"h0", "h1", "obs", "ds"}
    for rest in (s["rest_stopped"], s["rest_execute"]):
        assert set(rest["cpu_pct_per_cell"]) == set(rest["rss_mb_per_cell"]) == {"c0", "c1"}
        assert rest["cpu_pct_total"] > 0 and rest["rss_mb_total"] > 50
        assert rest["traffic"]["sent_bytes_per_min"] > 0
    line = s["line"]
    for verb in ("reset", "start", "floor"):
        assert line[verb]["p50_ms"] > 0 and line[verb]["p99_ms"] >= line[verb]["p50_ms"]
    assert line["start_p50_over_floor"] > 0
    cut = s["host_cut"]
    assert cut["host"] == "h0" and cut["units"] == 1 and cut["recovered"] is True
    assert 0 < cut["detect_s"] < cut["lease_s"] * 4 + 5 and cut["recover_s"] >= 0
    goals = s["goals"]
    assert set(goals) == {"ready_s", "rest_cpu_pct_per_cell", "rest_rss_total_mb",
                          "line_start_p50_ratio", "cut_detect_s", "recovered_without_a_hand"}  # fmt: skip
    assert goals["cut_detect_s"]["goal"] == 2.5  # the lease + 0.5 s
    for name, g in goals.items():
        if name != "recovered_without_a_hand":
            assert g["ratio_to_goal"] == pytest.approx(g["value"] / g["goal"], abs=1e-3)
            assert g["met"] == (g["value"] <= g["goal"]) and ("missed_by" in g) != g["met"]
    assert "simple" in "\n".join(result["table"]) and "simple" in err
    assert namespaces_of(proc.pid) == []
    # --em-lease reaches the cell files; --keep kept them beside every process's log
    assert result["em_lease_s"] == 3
    assert yaml.safe_load((kept / "simple/c0.yaml").read_text())["units"]["unit"]["em_lease"] == 3
    assert "PackML unit /c0/unit up" in (kept / "simple/c0.log").read_text()
    assert (kept / "simple/observer.log").exists()


def test_a_stage_that_fails_keeps_what_was_measured_before_it() -> None:
    proc = subprocess.Popen(
        [*PLANT, "--cells", "1", "--hosts", "1", "--window", "1", "--rest", "1", "--setups", "domains",
         "--ready-timeout", "0.5"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
    )  # fmt: skip
    out, err = proc.communicate(timeout=100)
    assert proc.returncode == 1, err[-3000:]
    s = json.loads(out)["setups"]["domains"]
    assert s["error"].startswith("at ready: domains: not every unit ready in 0.5 s: not ready: c0")
    assert "-- c0 on h0:" in s["error"]  # the late cell's last words
    assert "goals" in s and s["goals"]["ready_s"]["met"] is False
    assert "domains  error at ready" in err and "Traceback" not in err
    assert namespaces_of(proc.pid) == []


def test_plant_interrupted_removes_its_namespaces() -> None:
    proc = subprocess.Popen(
        [*PLANT, "--cells", "1", "--hosts", "1", "--window", "60", "--setups", "simple"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 30
        host = f"pl{proc.pid % 100000}h0"
        # the cell runs in its host: interrupt the benchmark in the middle of its work
        while not (host in namespaces_of(proc.pid) and ip("netns", "pids", host).stdout.split()):
            assert proc.poll() is None and time.monotonic() < deadline, (
                proc.stderr and proc.stderr.read()
            )
            time.sleep(0.1)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err[-3000:]
    assert "interrupted" in err and "Traceback" not in err
    assert namespaces_of(proc.pid) == []
