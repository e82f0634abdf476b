"""Issue 19, done when: on the demo cell, a jam in robot_cell followed by a full case packer
produces two stop episodes with the right root causes, the loss table per shift adds up to the
elapsed time, and ``packml report`` and the HMI page show it.

config/demo_cell.yaml runs as ``packml launch --hmi --opcua`` (faster, its stores in a temporary
directory) while ``packml record demo_cell`` records it; the README's commands of the line section
run verbatim in a shell; then the report (table, CSV, JSON), the HMI's line page in Chromium
(Playwright), the OPC UA face (node-opcua) and ``packml replay`` of the recording are checked."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

import pytest
import yaml
from packml_interfaces.msg import LineEpisode, Status

from packml_ros2 import qos
from packml_ros2.testing.harness import RosHarness
from packml_ros2.testing.launched import Launched
from test.hmi.test_browser import CHROMIUM_ARGS, sync_api

pytestmark = [pytest.mark.browser, pytest.mark.ros, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
README = (ROOT / "README.md").read_text()
SPEEDUP = 0.25
CHROMIUM = Path("/usr/bin/chromium")
PACKML = [sys.executable, "-m", "packml_ros2.cli.main"]


def readme_commands() -> list[str]:
    """The commands of the README's line section (``$ `` lines of its console block)."""
    section = README.split("## Line performance", 1)[1].split("\n## ", 1)[0]
    block = section.split("```console", 1)[1].split("```", 1)[0]
    return [
        line[2:].split("  #")[0].strip() for line in block.splitlines() if line.startswith("$ ")
    ]


def demo_cell(tmp: Path, opcua_port: int) -> Path:
    doc = yaml.safe_load((ROOT / "config" / "demo_cell.yaml").read_text())
    assert doc["cell"] == "demo_cell"
    doc["defaults"]["persistence"] = {"path": str(tmp / "{unit}.sqlite3")}
    doc["defaults"]["em_lease"] = 6.0  # a busy 2-core machine: no false EM loss
    for unit in doc["units"].values():
        for em in unit["equipment_modules"].values():
            sim = em["sim"]
            sim["durations"] = {k: round(v * SPEEDUP, 3) for k, v in sim.get("durations", {}).items()}  # fmt: skip
            sim["cycle_time"] = round(sim["cycle_time"] * SPEEDUP, 3)
            if "buffer" in sim:
                sim["buffer"] = sim["buffer"] * SPEEDUP
            sim["lease"] = 6.0
        for key in ("mach_speed", "mach_design_speed"):
            unit[key] = round(unit[key] / SPEEDUP, 3)
    doc["line"]["publish_period"] = 1.0
    doc["hmi"] = {"host": "127.0.0.1", "port": 0}
    doc["opcua"] = {"host": "127.0.0.1", "port": opcua_port, "state_dir": str(tmp / "opcua"),
                    "security_policies": ["None"]}  # fmt: skip
    path = tmp / "demo_cell.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def launched_with_opcua(cell_file: Path, log: Path) -> Launched:
    """``packml launch <cell> --hmi --opcua`` in the background, its output waited on."""
    return Launched([*PACKML, "launch", str(cell_file), "--hmi", "--opcua"], log)


def run_sh(command: str, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    """``command`` in bash, with this Python's environment's ``packml`` first on the PATH."""
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
    return subprocess.run(["bash", "-c", command], capture_output=True, text=True, env=env, timeout=timeout, check=False)  # fmt: skip


def sh(command: str, timeout: float = 60.0) -> str:
    done = run_sh(command, timeout)
    assert done.returncode == 0, f"$ {command}\n{done.stdout}\n{done.stderr}"
    return done.stdout


def test_jam_then_full_packer_on_the_demo_cell(tmp_path: Path, ros_domain: int) -> None:
    from test.opcua.test_opcua import NodeClient, free_port

    port = free_port()
    cell_file = demo_cell(tmp_path, port)
    launched = launched_with_opcua(cell_file, tmp_path / "launch.log")
    ros = RosHarness(ros_domain)
    recorder: subprocess.Popen[bytes] | None = None
    client = NodeClient(tmp_path / "node_client.log", tmp_path / "pki")
    try:
        url = launched.wait_for(r"PackML HMI for cell \S+: (http://127\.0\.0\.1:\d+/)").group(1)
        launched.wait_for("is up")
        launched.wait_for("OPC UA server for cell")
        status = {u: ros.subscribe(Status, f"/demo_cell/{u}/status", qos.STATUS) for u in ("robot_cell", "case_packer")}  # fmt: skip
        episodes = ros.subscribe(LineEpisode, "/demo_cell/coordinator/line/episodes", qos.LINE_EPISODES)  # fmt: skip
        for collector in status.values():
            collector.wait_for(lambda m: True, 30, "a status")
        log = (tmp_path / "record.log").open("wb")
        recorder = subprocess.Popen([*PACKML, "record", "demo_cell", "-o", str(tmp_path / "bag")],
                                    stdout=log, stderr=subprocess.STDOUT)  # fmt: skip
        wait_for_file(tmp_path / "record.log", "recording")

        commands = readme_commands()
        assert commands[:2] == ["packml cmd demo_cell reset && packml cmd demo_cell start",
                                "packml fault robot_cell/infeed jam on"], commands  # fmt: skip
        steps: dict[str, Any] = {
            # after each command: what the cell does before the next one is typed
            "packml fault robot_cell/infeed jam on": lambda: status["case_packer"].wait_for(
                lambda m: m.state_current_name == "SUSPENDED", 20, "the packer starved"),
            "packml fault robot_cell/infeed jam off": lambda: status["robot_cell"].wait_for(
                lambda m: m.active_alarms == 0, 20, "the jam cleared at robot_cell"),
            "packml fault case_packer/loader full on": lambda: status["robot_cell"].wait_for(
                lambda m: m.state_current_name == "SUSPENDED", 20, "robot_cell suspended by the coordinator"),
            "packml fault case_packer/loader full off": lambda: episodes.wait_for(
                lambda e: e.id == 2 and not e.open, 20, "episode 2 closed"),
        }  # fmt: skip
        outputs = {}
        for command in commands:
            outputs[command] = sh(command)
            if command in steps:
                steps[command]()
            if command.startswith("packml cmd robot_cell reset"):
                episodes.wait_for(lambda e: e.id == 1 and not e.open, 20, "episode 1 closed")

        # -- the episodes: jam in robot_cell (the packer starved), then the full packer
        report = json.loads(sh("packml report --format json --since 1h"))
        eps = sorted(report["episodes"], key=lambda e: e["id"])
        assert [(e["id"], e["root_unit"], e["bucket"], e["reason"]) for e in eps] == [
            (1, "robot_cell", "unplanned_stop", "alarm 202: Infeed jam"),
            (2, "case_packer", "blocked", "loader blocked")], eps  # fmt: skip
        assert {(a["unit"], a["how"]) for a in eps[0]["affected"]} == {("robot_cell", "internal"), ("case_packer", "starved")}  # fmt: skip
        assert {(a["unit"], a["how"]) for a in eps[1]["affected"]} == {("case_packer", "blocked"), ("robot_cell", "propagated")}  # fmt: skip
        assert eps[0]["stop_reason"]["id"] == 202 and eps[0]["source"] == "alarm:202"

        # -- the loss table of the shift adds up to its elapsed time, in every scope
        shift = json.loads(sh("packml report --format json"))
        assert shift["window"].startswith("shift:")
        for scope in shift["scopes"]:
            ns = scope["nanoseconds"]
            parts = ("planned_stop", "unplanned_stop", "blocked", "starved", "held", "speed_loss", "quality_loss", "productive")  # fmt: skip
            assert sum(ns[p] for p in parts) == ns["elapsed"] > 0, scope
        line = shift["scopes"][0]
        reasons = {(b["bucket"], b["reason"]) for b in line["buckets"]}
        assert {("unplanned_stop", "robot_cell: alarm 202: Infeed jam"), ("blocked", "case_packer: loader blocked")} <= reasons  # fmt: skip
        table = outputs["packml report"]
        assert (
            "robot_cell: alarm 202: Infeed jam" in table and "case_packer: loader blocked" in table
        )
        # the episodes as the README shows them (all but the times)
        shown = (
            README.split("`packml report` prints", 1)[1].split("```text", 1)[1].split("```", 1)[0]
        )
        assert shown.strip().splitlines()[0] in table, table

        def columns(text: str) -> list[list[str]]:
            rows = [
                re.split(r"\s{2,}", x.strip())
                for x in text.splitlines()
                if re.match(r"^  \d+  ", x)
            ]
            return [[r[0], *r[3:]] for r in rows]

        assert len(columns(shown)) == 2
        assert columns(shown) == columns(table.split("STOP EPISODES", 1)[1]), table
        total = re.search(r"^  total\s+(\S+)\s+100\.0%$", table, re.M)
        elapsed = re.search(r"^  elapsed\s+(\S+)$", table, re.M)
        assert total and elapsed and total.group(1) == elapsed.group(1), table
        csv_rows = [r.split(",") for r in outputs["packml report --format csv --since 1h"].splitlines()[1:]]  # fmt: skip
        line_rows = [r for r in csv_rows if r[3] == "line"]
        assert abs(sum(float(r[-1]) for r in line_rows if r[4] != "elapsed") - next(float(r[-1]) for r in line_rows if r[4] == "elapsed")) < 0.01  # fmt: skip

        # -- refused, with the reason and no traceback
        for command, code, why in (
            ('packml report --shift "2020-01-01 lunch"', 1, "no shift '2020-01-01 lunch' in the calendar"),
            ("packml report --since 9999-12-31T00:00", 2, "is not a time between 1970 and 2038"),
            ("packml report --since yesterday", 2, "'yesterday' is not a time"),
        ):  # fmt: skip
            done = run_sh(command)
            assert done.returncode == code and why in done.stderr, (command, done.stdout, done.stderr)  # fmt: skip
            assert "Traceback" not in done.stderr + done.stdout

        # -- the HMI's line page
        check_page(url, tmp_path)
        for query, status in (("?shift=%3Cscript%3E", 400), ("?shift=2020-01-01%20lunch", 404), ("?shift=" + "9" * 5000, 400)):  # fmt: skip
            with pytest.raises(urllib.error.HTTPError) as refused:
                urllib.request.urlopen(f"{url}api/line{query}", timeout=10)
            body = json.loads(refused.value.read())
            assert refused.value.code == status and body["message"], body

        # -- OPC UA: the line's OEE and its last episode
        client.wait_ready()
        base = "U:Lines/U:demo_cell"
        got = client.job(f"opc.tcp://127.0.0.1:{port}/", [
            {"op": "read", "path": f"{base}/U:CurrentEpisode/U:RootCauseUnit"},
            {"op": "read", "path": f"{base}/U:CurrentEpisode/U:Reason"},
            {"op": "read", "path": f"{base}/U:CurrentEpisode/U:Open"},
            {"op": "read", "path": f"{base}/U:OEE"},
            {"op": "read", "path": f"{base}/U:Window"}])  # fmt: skip
        assert [r["value"] for r in got[:3]] == ["case_packer", "loader blocked", False], got
        assert got[3]["status"] == "Good" and 0.0 < got[3]["value"] < 1.0, got
        assert got[4]["value"].startswith("shift:"), got
    finally:
        client.close()
        if recorder is not None:
            recorder.send_signal(signal.SIGINT)
            recorder.wait(30)
        ros.close()
        code = launched.stop()
    assert code == 0, launched.output()[-3000:]
    assert "Traceback" not in launched.output(), launched.output()[-3000:]

    # -- the recording replays: the line's episodes and losses are made again exactly
    replay = subprocess.run([*PACKML, "replay", str(tmp_path / "bag")],
                            capture_output=True, text=True, timeout=300, check=False)  # fmt: skip
    assert replay.returncode == 0, replay.stdout + replay.stderr
    assert re.search(r"line demo_cell: match \(\d+ inputs; (\d+) episodes, (\d+) losses compared\)", replay.stdout), replay.stdout  # fmt: skip
    compared = re.search(r"(\d+) episodes, (\d+) losses compared", replay.stdout)
    assert compared and int(compared.group(1)) >= 6 and int(compared.group(2)) >= 10, replay.stdout


def wait_for_file(path: Path, text: str, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while text not in path.read_text(errors="replace"):
        assert time.monotonic() < deadline, path.read_text(errors="replace")
        time.sleep(0.05)


def check_page(url: str, tmp: Path) -> None:
    shots = Path(os.environ.get("PACKML_SCREENSHOTS_DIR") or tmp)
    with sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS, headless=True)  # fmt: skip
        try:
            page = browser.new_page(viewport={"width": 1440, "height": 1300})
            problems: list[str] = []
            page.on("console", lambda m: m.type == "error" and problems.append(m.text))
            page.on("pageerror", lambda e: problems.append(str(e)))
            page.on("request", lambda r: r.url.startswith(url.rstrip("/")) or problems.append(f"request: {r.url}"))  # fmt: skip
            page.goto(f"{url}line")
            page.wait_for_selector("body[data-loaded='1']", timeout=20_000)
            rows = page.locator("#episodes tbody tr")
            assert rows.count() == 2
            assert "case_packer" in rows.nth(0).inner_text() and "loader blocked" in rows.nth(0).inner_text()  # fmt: skip
            assert "alarm 202: Infeed jam" in rows.nth(1).inner_text()
            assert page.inner_text("#episode-root") == "case_packer"
            pareto = page.evaluate("Chart.getChart('pareto').data.labels")
            assert sorted(pareto) == ["case_packer: loader blocked", "robot_cell: alarm 202: Infeed jam"]  # fmt: skip
            waterfall = page.evaluate("Chart.getChart('waterfall').data.labels")
            assert waterfall[0] == "elapsed" and waterfall[-1] == "productive"
            bars = page.evaluate("Chart.getChart('waterfall').data.datasets[0].data")
            assert abs(bars[-2][0] - bars[-1][1]) < 1e-6  # the last loss ends where productive ends
            assert page.evaluate("Chart.getChart('trend').data.datasets.length") == 4
            assert page.locator("#losses tbody tr").count() == 3
            assert page.inner_text("[data-kpi='OEE']").endswith("%")
            page.screenshot(path=str(shots / "hmi-line.png"), full_page=True)
            assert not problems, problems
            # the overview links to it
            page.goto(url)
            assert page.get_attribute("#nav-line", "href") == "/line"
        finally:
            browser.close()
