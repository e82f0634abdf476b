"""Command-line benchmark: how long the ``packml`` verbs take on a running demo cell, side by side
with the floor measured in the same run (a process that imports rclpy and the interfaces, starts a
node, receives one latched ``status`` of a unit whose name it already knows, and exits: what any
read-only verb has to do at least). Prints JSON.

    python bench/cli.py [--runs 10]

Read-only verbs (``packml status``, ``packml status robot_cell``, ``packml alarms``): wall time
per run. Commands (``packml cmd robot_cell hold`` / ``unhold`` in Execute): wall time, the time
the unit took to settle as the verb prints it ("now HELD (0.61 s)"), and the difference: what the
verb adds to the unit's own work. The cell (config/demo_cell.yaml, ``packml launch``, one process)
runs in a ROS domain of its own, localhost only, with its admin data in a temporary directory.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from packml_ros2.testing.environment import allocate_domain, localhost_environment

ROOT = Path(__file__).resolve().parents[1]
PACKML = [sys.executable, "-m", "packml_ros2.cli.main"]
FLOOR = """
import rclpy
from rclpy.node import Node
from packml_interfaces.msg import Status
from packml_ros2 import qos
rclpy.init()
node = Node("cli_floor")
got = []
node.create_subscription(Status, "/demo_cell/robot_cell/status", got.append, qos.STATUS)
while not got:
    rclpy.spin_once(node, timeout_sec=1.0)
node.destroy_node()
rclpy.shutdown()
"""
SETTLED = re.compile(r"now \w+ \(([\d.]+) s\)")


def timed(argv: list[str], env: dict[str, str]) -> tuple[float, str]:
    t0 = time.perf_counter()
    done = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=120, check=False)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise RuntimeError(
            f"{' '.join(argv[2:])}: exit {done.returncode}\n{done.stdout}{done.stderr}"
        )
    return wall, done.stdout


def summary(values: list[float]) -> dict[str, object]:
    ordered = sorted(values)
    return {
        "median_s": round(statistics.median(values), 3),
        "p90_s": round(ordered[min(len(ordered) - 1, int(0.9 * len(ordered)))], 3),
        "runs_s": [round(v, 3) for v in values],
    }


def start_cell(env: dict[str, str], log: Path) -> subprocess.Popen[bytes]:
    cell = subprocess.Popen(
        [*PACKML, "launch", str(ROOT / "config" / "demo_cell.yaml")],
        env=env,
        stdout=log.open("wb"),
        stderr=subprocess.STDOUT,
    )
    deadline = time.monotonic() + 90
    while "is up" not in log.read_text(errors="replace"):
        if cell.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f"the demo cell did not come up:\n{log.read_text()}")
        time.sleep(0.1)
    return cell


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--runs", type=int, default=10)
    args = parser.parse_args()
    localhost_environment()
    os.environ["ROS_DOMAIN_ID"] = str(allocate_domain())
    with tempfile.TemporaryDirectory(prefix="packml_bench_cli_") as tmp:
        env = dict(os.environ, HOME=tmp, PYTHONUNBUFFERED="1")
        cell = start_cell(env, Path(tmp) / "cell.log")
        try:
            for command in ("reset", "start"):
                timed([*PACKML, "cmd", "demo_cell", command], env)
            floor = [timed([sys.executable, "-c", FLOOR], env)[0] for _ in range(args.runs)]
            read_only = {
                "packml status": [*PACKML, "status"],
                "packml status robot_cell": [*PACKML, "status", "robot_cell"],
                "packml alarms": [*PACKML, "alarms"],
            }
            results: dict[str, object] = {}
            for name, argv in read_only.items():
                walls = [timed(argv, env)[0] for _ in range(args.runs)]
                results[name] = {
                    **summary(walls),
                    "ratio_to_floor": round(statistics.median(walls) / statistics.median(floor), 2),
                }
            for verb in ("hold", "unhold"):
                results[f"packml cmd robot_cell {verb}"] = {"wall_s": [], "settle_s": []}
            for _ in range(max(1, args.runs // 2)):
                for verb in ("hold", "unhold"):
                    wall, out = timed([*PACKML, "cmd", "robot_cell", verb], env)
                    settled = SETTLED.search(out)
                    entry = results[f"packml cmd robot_cell {verb}"]
                    assert isinstance(entry, dict)
                    entry["wall_s"].append(round(wall, 3))
                    entry["settle_s"].append(float(settled.group(1)) if settled else 0.0)
            for verb in ("hold", "unhold"):
                entry = results[f"packml cmd robot_cell {verb}"]
                assert isinstance(entry, dict)
                extra = [w - s for w, s in zip(entry["wall_s"], entry["settle_s"], strict=True)]
                entry["median_wall_s"] = round(statistics.median(entry["wall_s"]), 3)
                entry["median_settle_s"] = round(statistics.median(entry["settle_s"]), 3)
                entry["median_overhead_s"] = round(statistics.median(extra), 3)
        except Exception:
            print((Path(tmp) / "cell.log").read_text(errors="replace")[-4000:], file=sys.stderr)
            raise
        finally:
            cell.send_signal(2)
            cell.wait(30)
    print(
        json.dumps(
            {
                "floor (a process receives one latched status)": summary(floor),
                **results,
                "target": "read-only verbs: median <= 1 s",
                "met": all(
                    r["median_s"] <= 1.0  # type: ignore[index]
                    for k, r in results.items()
                    if not k.startswith("packml cmd")
                ),
            },
            indent=2,
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
