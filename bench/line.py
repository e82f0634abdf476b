"""A line of cells, measured: a line-wide reset and start through the line's coordinator, each
cell reached over its OPC 30050 face (``opcua.cell_object``, one PLC bridge per cell), against the
floor of the same calls made by a bare client in the same run. Prints JSON.

    python bench/line.py [--cells 4] [--ems 2] [--cycles 10] [--publishing-interval 0.1]

Each cell is one unit with ``--ems`` simulated EMs whose acting states take no time (what is
measured is messaging, not a machine's motion), its coordinator and its OPC UA face, started by
``packml launch cell.yaml --opcua`` in a ROS domain of its own; the line is ``packml launch
line.yaml`` in another domain: one bridge per cell and the line's coordinator, which sequences the
cells in their order (each answered once the cell's units took the command).

- ``line``: this process calls the line coordinator's ``reset`` / ``start`` (std_srvs/Trigger)
  and waits for the answer and for the line's status to show every cell in Idle / Execute;
- ``floor``: the same cells, the same order, called directly: this process calls each cell
  coordinator's ``reset`` / ``start`` in its domain, one after the other as the line does, and
  waits for every cell's status to show the state. What the line adds above it is the line's
  coordinator, one bridge and one OPC UA call per cell.

The two alternate in every cycle (under the same load); a stop between them is not measured.
Everything stays on this machine (loopback, domains of its own).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from plant import Domain, summary_ms  # (one way to follow a domain and to sum up)

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

GOAL_RATIO = 1.5  # issue 29: a line-wide start p50 against its bare-client floor
PASSWORD = "bench-line-pw"
ZERO = dict.fromkeys(("resetting", "starting", "stopping", "clearing", "aborting"), 0.0)


class Cells:
    """The statuses (CellStatus) this process follows and the Trigger services it calls."""

    def __init__(self) -> None:
        self.cond = threading.Condition()
        self.latest: dict[str, Any] = {}
        self.clients: dict[tuple[str, str], Any] = {}

    def follow(self, domain: Domain, cell: str) -> None:
        from packml_interfaces.msg import CellStatus
        from std_srvs.srv import Trigger

        from packml_ros2 import qos

        def on_status(msg: Any) -> None:
            with self.cond:
                self.latest[cell] = msg
                self.cond.notify_all()

        domain.node.create_subscription(
            CellStatus, f"/{cell}/coordinator/status", on_status, qos.CELL_STATUS
        )
        for verb in ("reset", "start", "stop"):
            self.clients[(cell, verb)] = domain.node.create_client(
                Trigger, f"/{cell}/coordinator/{verb}"
            )

    def wait(self, done: Any, timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        with self.cond:
            while not done():
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"{what} not within {timeout:g} s")
                self.cond.wait(left)

    def call(self, cell: str, verb: str, timeout: float = 60.0) -> None:
        from std_srvs.srv import Trigger

        client = self.clients[(cell, verb)]
        if not client.wait_for_service(timeout_sec=timeout):
            raise TimeoutError(f"/{cell}/coordinator/{verb} not available")
        done = threading.Event()
        future = client.call_async(Trigger.Request())
        future.add_done_callback(lambda _: done.set())
        if not done.wait(timeout):
            raise TimeoutError(f"/{cell}/coordinator/{verb}: no answer within {timeout:g} s")
        answer = future.result()
        if not answer.success:
            raise RuntimeError(f"/{cell}/coordinator/{verb} refused: {answer.message}")

    def unit_states(self, cell: str) -> dict[str, str]:
        msg = self.latest.get(cell)
        return {} if msg is None else {u.name: u.state_current_name for u in msg.units if u.online}


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    parser.add_argument("--cells", type=int, default=4, help="cells in the line (default 4)")
    parser.add_argument("--ems", type=int, default=2, help="simulated EMs per cell's unit")
    parser.add_argument("--cycles", type=int, default=10, help="measured cycles (default 10)")
    parser.add_argument("--publishing-interval", type=float, default=0.1,
                        help="the bridges' plc.publishing_interval, s (default 0.1, its default)")  # fmt: skip
    parser.add_argument("--keep", type=Path, help="keep the cell files and logs here")
    args = parser.parse_args()

    from packml_ros2.opcua.config import hash_password
    from packml_ros2.testing.environment import allocate_domain, localhost_environment

    localhost_environment()
    line_domain = allocate_domain()
    os.environ["ROS_DOMAIN_ID"] = str(line_domain)
    work = Path(tempfile.mkdtemp(prefix="bench_line_")) if args.keep is None else args.keep
    work.mkdir(parents=True, exist_ok=True)
    (work / "line").mkdir(exist_ok=True)
    secret = work / "line.pw"
    secret.write_text(PASSWORD)
    secret.chmod(0o600)
    tag = f"bl{os.getpid() % 100000}"
    cells = [f"{tag}c{i}" for i in range(args.cells)]
    domains = {cell: allocate_domain() for cell in cells}
    line_units: dict[str, Any] = {}
    for cell in cells:
        port = free_port()
        folder = work / cell
        folder.mkdir(exist_ok=True)
        ems = {f"em{j}": {"sim": {"durations": ZERO, "cycle_time": 1.0}} for j in range(args.ems)}
        doc = {
            "cell": cell,
            "discovery": {"domain": domains[cell]},
            "units": {"robot": {"remote_commands_enabled": True, "equipment_modules": ems,
                                "persistence": {"path": str(folder / "{unit}.sqlite3")}}},
            "opcua": {"port": port, "cell_object": True, "state_dir": str(folder / "opcua"),
                      "users": {"line": hash_password(PASSWORD, iterations=1000)}},
        }  # fmt: skip
        (folder / "cell.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
        line_units[cell] = {
            "remote_commands_enabled": True,
            "persistence": {"path": str(work / "line" / "{unit}.sqlite3")},
            "plc": {"endpoint": f"opc.tcp://127.0.0.1:{port}/", "browse_path": f"PackMLObjects/{cell}",
                    "user": "line", "password": f"file:{secret}", "security_policy": "Basic256Sha256",
                    "state_dir": str(work / "bridges"), "call_timeout": 30.0,
                    "publishing_interval": args.publishing_interval},
        }  # fmt: skip
    line = f"{tag}line"
    line_doc = {"cell": line, "units": line_units,
                "coordinator": {"start_order": cells, "step_timeout": 30.0}}  # fmt: skip
    (work / "line.yaml").write_text(yaml.safe_dump(line_doc, sort_keys=False))

    procs: list[subprocess.Popen[bytes]] = []

    def launch(name: str, *argv: str) -> None:
        log = (work / f"{name}.log").open("ab")
        procs.append(subprocess.Popen(
            [sys.executable, "-m", "packml_ros2.cli.main", "launch", *argv],
            cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
        ))  # fmt: skip

    for cell in cells:
        launch(cell, str(work / cell / "cell.yaml"), "--opcua")
    launch("line", str(work / "line.yaml"))
    ros = {d: Domain(d, "bench_line") for d in {line_domain, *domains.values()}}
    watch = Cells()
    watch.follow(ros[line_domain], line)
    for cell in cells:
        watch.follow(ros[domains[cell]], cell)
    result: dict[str, Any] = {"cells": args.cells, "ems_per_cell": args.ems, "cycles": args.cycles,
                              "publishing_interval_s": args.publishing_interval}  # fmt: skip
    try:
        ready_at = time.monotonic()
        watch.wait(
            lambda: len(watch.unit_states(line)) == args.cells, 120, "every cell in the line"
        )
        result["ready_s"] = round(time.monotonic() - ready_at, 2)
        samples: dict[str, list[float]] = {"line_reset": [], "line_start": [],
                                           "floor_reset": [], "floor_start": []}  # fmt: skip

        def all_in(state: str) -> bool:
            return watch.unit_states(line) == dict.fromkeys(cells, state) and all(
                watch.unit_states(c) == {"robot": state} for c in cells
            )

        def by_line(verb: str, state: str) -> float:
            t0 = time.monotonic()
            watch.call(line, verb)
            watch.wait(lambda: all_in(state), 60, f"the line in {state}")
            return time.monotonic() - t0

        def by_floor(verb: str, state: str) -> float:
            t0 = time.monotonic()
            for cell in cells:
                watch.call(cell, verb)
            watch.wait(lambda: all_in(state), 60, f"the cells in {state}")
            return time.monotonic() - t0

        def stop() -> None:
            for cell in reversed(cells):
                watch.call(cell, "stop")
            watch.wait(lambda: all_in("STOPPED"), 60, "the cells stopped")

        watch.wait(lambda: all_in("STOPPED"), 60, "every cell stopped")
        for i in range(args.cycles + 1):  # the first cycle warms up
            for way, run in (("line", by_line), ("floor", by_floor)):
                took = [run("reset", "IDLE"), run("start", "EXECUTE")]
                stop()
                if i:
                    samples[f"{way}_reset"].append(took[0])
                    samples[f"{way}_start"].append(took[1])
        for key, values in samples.items():
            result[key] = summary_ms(values)
            result[key]["samples_ms"] = [round(v * 1000, 1) for v in values]
        for verb in ("reset", "start"):
            ratio = result[f"line_{verb}"]["p50_ms"] / result[f"floor_{verb}"]["p50_ms"]
            result[f"{verb}_p50_over_floor"] = round(ratio, 2)
        result["goal_start_p50_over_floor"] = GOAL_RATIO
        result["goal_met"] = result["start_p50_over_floor"] <= GOAL_RATIO
        result["per_cell_added_ms"] = round(
            (result["line_start"]["p50_ms"] - result["floor_start"]["p50_ms"]) / args.cells, 1
        )
    finally:
        for p in procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGINT)
        for p in procs:
            try:
                p.wait(20)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
        for d in ros.values():
            d.close()
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
