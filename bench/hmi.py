"""HMI benchmark: how long after a unit publishes a status the operator's page shows it. The demo
cell runs as `packml launch <cell> --hmi` (units, simulated EMs, coordinator, HMI server); Debian's
headless Chromium shows robot_cell's screen; this process commands Reset / Start / Stop cycles
over ROS and subscribes to the unit's status itself. For every status it receives, the first time
the page applied that status or a newer one to its screen (``window.__hmi.renders``: the wall
clock of the same machine) is looked up. Side by side, in the same run, the floor: the same status
reaching this process's own subscription (one DDS hop; the page's path adds the HMI server's hop
and the browser). Prints JSON: medians, 95th percentiles and the ratio to the floor.

    python bench/hmi.py [--cycles 5]

Everything stays on this machine (loopback, a ROS domain of its own). The browser tests assert
what the page shows, never how fast: this is where the speed is measured.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import yaml

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = Path("/usr/bin/chromium")
SPEEDUP = 0.25  # the demo's simulated durations, shortened (as the browser tests do)


def cell_file(tmp: Path) -> Path:
    doc = yaml.safe_load((ROOT / "config" / "demo_cell.yaml").read_text())
    doc["cell"] = f"hmibench{os.getpid()}"
    doc["defaults"]["persistence"] = {"path": str(tmp / "{unit}.sqlite3")}
    for unit in doc["units"].values():
        for em in unit["equipment_modules"].values():
            sim = em["sim"]
            sim["durations"] = {
                k: round(v * SPEEDUP, 3) for k, v in sim.get("durations", {}).items()
            }
            sim["cycle_time"] = round(sim["cycle_time"] * SPEEDUP, 3)
            sim.pop("fed_by", None)
            sim.pop("buffer", None)
    doc["hmi"] = {"host": "127.0.0.1", "port": 0, "title": "bench"}
    path = tmp / "cell.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def pct(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(q * (len(ordered) - 1)))]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cycles", type=int, default=5, help="Reset/Start/Stop cycles")
    args = parser.parse_args()

    from packml_ros2.testing.environment import allocate_domain, localhost_environment

    localhost_environment()
    os.environ["ROS_DOMAIN_ID"] = str(allocate_domain())
    from packml_interfaces.msg import Status
    from packml_interfaces.srv import Command
    from playwright.sync_api import sync_playwright

    from packml_ros2 import qos
    from packml_ros2.core import Cmd
    from packml_ros2.testing.harness import RosHarness
    from packml_ros2.testing.launched import Launched

    if not CHROMIUM.exists():
        raise SystemExit("Debian's chromium (/usr/bin/chromium) is needed")
    unit = "robot_cell"
    with tempfile.TemporaryDirectory() as tmp:
        path = cell_file(Path(tmp))
        cell = yaml.safe_load(path.read_text())["cell"]
        cli = [sys.executable, "-m", "packml_ros2.cli.main"]
        launched = Launched([*cli, "launch", str(path), "--hmi"], Path(tmp) / "launch.log")
        ros = RosHarness(int(os.environ["ROS_DOMAIN_ID"]))
        receipts: list[tuple[int, float, float]] = []  # sequence, stamp ms, received ms

        def note(msg: Any) -> None:
            received = time.time() * 1000.0
            receipts.append(
                (msg.sequence, msg.stamp.sec * 1000.0 + msg.stamp.nanosec / 1e6, received)
            )

        status = ros.subscribe(Status, f"/{cell}/{unit}/status", qos.STATUS)
        ros.node.create_subscription(Status, f"/{cell}/{unit}/status", note, qos.STATUS)
        playwright = sync_playwright().start()
        try:
            url = launched.wait_for(r"PackML HMI for cell \S+: (http://127\.0\.0\.1:\d+/)").group(1)
            launched.wait_for("is up")
            browser = playwright.chromium.launch(
                executable_path=str(CHROMIUM), headless=True, args=["--no-sandbox", "--disable-gpu"]
            )
            page = browser.new_page()
            page.goto(f"{url}#/unit/{unit}")
            page.wait_for_selector("#diagram")
            status.wait_for(lambda m: True, 30, "a status")
            page.wait_for_function("window.__hmi.renders.length > 0 || window.__hmi.connected")
            first = len(receipts)
            for _ in range(args.cycles):
                for cmd, state in (
                    (Cmd.RESET, "IDLE"),
                    (Cmd.START, "EXECUTE"),
                    (Cmd.STOP, "STOPPED"),
                ):
                    start = len(status)
                    answer = ros.call(
                        Command,
                        f"/{cell}/{unit}/command",
                        Command.Request(command=int(cmd), source="operator:bench"),
                    )
                    assert answer.accepted, answer.message
                    status.wait_for(lambda m, s=state: m.state_current_name == s, 30, state, start)
            last = receipts[-1]
            page.wait_for_function(  # the last status is on the page: every earlier one is done
                "stamp => window.__hmi.renders.some(r => r.stamp > stamp - 0.01)", arg=last[1]
            )
            renders = page.evaluate("window.__hmi.renders")
            browser.close()
        finally:
            playwright.stop()
            ros.close()
            launched.stop()
    page_ms, floor_ms = [], []
    for _seq, stamp, received in receipts[first:]:
        shown = [r["rendered"] for r in renders if r["unit"] == unit and r["stamp"] > stamp - 0.01]
        if shown:
            page_ms.append(min(shown) - stamp)
            floor_ms.append(received - stamp)
    out = {
        "cycles": args.cycles,
        "statuses": len(page_ms),
        "publish_to_page_ms": {
            "p50": round(statistics.median(page_ms), 2),
            "p95": round(pct(page_ms, 0.95), 2),
            "max": round(max(page_ms), 2),
        },
        "floor_publish_to_subscriber_ms": {
            "p50": round(statistics.median(floor_ms), 2),
            "p95": round(pct(floor_ms, 0.95), 2),
        },
        "ratio_p50": round(statistics.median(page_ms) / max(statistics.median(floor_ms), 1e-6), 2),
        "load_average": os.getloadavg()[0],
    }
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
