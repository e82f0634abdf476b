"""Scale curve: what a cell costs at rest and how fast it answers as it grows. Prints JSON.

    python bench/scale.py [--ems 1,8,32] [--units 1,5,20] [--idle 10] [--cycles 20]

Each case is a cell file run by ``packml launch`` in one process (in-process nodes: the larger
cases would not fit on 2 cores as processes), with simulated EMs that take no time:

- ``ems``: one unit with 1, 8, 32 EMs; the command is the unit's ``start`` (Idle -> Execute seen
  on its ``status``);
- ``units``: 1, 5, 20 units (no EMs) on one coordinator; the command is the coordinator's
  ``start`` (the cell Idle -> Execute seen on the coordinator's ``status``).

The demo cell (config/demo_cell.yaml) in one process: idle CPU in Stopped and in Execute.

Idle CPU (percent of one core, the process's user + system time over ``--idle`` seconds) and RSS
are measured in Stopped; the floor beside them is a process that imports rclpy and spins one node
(``floor``). ``per_em`` / ``per_unit``: the growth from the smallest to the largest case, divided
by the nodes added. Everything stays on this machine (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST) in
a domain of its own.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from ros_latency import Client, percentile, rss_mb

from packml_ros2.testing.environment import allocate_domain, localhost_environment

FLOOR = """
import sys
from rclpy.node import Node
from packml_ros2 import run
run.init()
sys.exit(run.spin([Node("scale_floor")]))
"""
HZ = os.sysconf("SC_CLK_TCK")
#: who asks (the source grammar of the services: the operator at the machine, by name)
BENCH_SOURCE = "operator:bench"


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / HZ  # utime + stime


def idle_cpu(pid: int, seconds: float) -> float:
    """Percent of one core ``pid`` used over ``seconds``."""
    t0, c0 = time.monotonic(), cpu_seconds(pid)
    time.sleep(seconds)
    return round((cpu_seconds(pid) - c0) / (time.monotonic() - t0) * 100, 2)


#: s a cell is left after its start before its idle CPU is measured: a warm-up of the measurement
#: (discovery, first and latched publications end), not a wait for an event
SETTLE = 2.0


def at_rest(pid: int, seconds: float, settle: float = SETTLE) -> dict[str, object]:
    """Idle CPU (percent of one core over ``seconds``) and RSS of ``pid`` after ``settle``."""
    time.sleep(settle)
    return {"idle_cpu_pct": idle_cpu(pid, seconds), "rss_mb": rss_mb(pid)}


def ems_cell(n: int) -> dict[str, object]:
    sim = {"cycle_time": 0, "counter": "none", "lease": 2.0}
    return {
        "units": {"unit": {"equipment_modules": {f"em{i}": {"sim": sim} for i in range(n)}}},
        "coordinator": {"enabled": False},
    }


def units_cell(n: int) -> dict[str, object]:
    return {
        "defaults": {"remote_commands_enabled": True},
        "units": {f"u{i}": {} for i in range(n)},
    }


class Launched:
    """``packml launch <cell>`` in one process, until :meth:`stop`."""

    def __init__(self, workdir: Path, name: str, doc: dict[str, object]) -> None:
        doc = {**doc, "cell": name}
        for i, unit in enumerate(doc["units"].values()):  # type: ignore[attr-defined]
            unit["persistence"] = {"path": str(workdir / f"{name}_{i}.sqlite3")}
        cell_file = workdir / f"{name}.yaml"
        cell_file.write_text(yaml.safe_dump(doc))
        self.log = workdir / f"{name}.log"
        self._out = self.log.open("wb")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "packml_ros2.cli.main", "launch", str(cell_file)],
            stdout=self._out,
            stderr=subprocess.STDOUT,
        )
        deadline = time.monotonic() + 120
        while "is up" not in self.log.read_text(errors="replace"):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.stop()
                raise RuntimeError(f"{name} did not come up:\n{self.log.read_text()[-2000:]}")
            time.sleep(0.1)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(2)
            try:
                self.proc.wait(20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._out.close()


def unit_latency(
    client: Client, topic: str, triggers: dict[str, object], cycles: int
) -> dict[str, float]:
    """Reset, then ``cycles`` times start (timed until ``topic`` shows Execute), stop, reset."""

    def state_is(name: str):  # type: ignore[no-untyped-def]
        return lambda m: m.state_current_name == name

    client.call(triggers["reset"])
    client.wait(topic, state_is("IDLE"), 30)
    samples = []
    for i in range(cycles + 3):
        t0 = client.call(triggers["start"])
        _, t1 = client.wait(topic, state_is("EXECUTE"), 30)
        client.call(triggers["stop"])
        client.wait(topic, state_is("STOPPED"), 30)
        client.call(triggers["reset"])
        client.wait(topic, state_is("IDLE"), 30)
        if i >= 3:  # warm-up
            samples.append(t1 - t0)
    return summary(samples)


def cell_latency(service, commands: dict[str, int], cycles: int) -> dict[str, float]:  # type: ignore[no-untyped-def]
    """The coordinator answers a cell command once every unit got there (or why not): reset,
    then ``cycles`` times start (timed until its answer), stop, reset."""
    from packml_interfaces.srv import Command

    def call_timed(c: str) -> float:
        t0 = time.perf_counter()
        answer = call(service, Command.Request(command=commands[c], source=BENCH_SOURCE))
        if not answer.accepted:
            raise RuntimeError(f"coordinator {c}: {answer.message}")
        return time.perf_counter() - t0

    call_timed("reset")
    samples = []
    for i in range(cycles + 3):
        took = call_timed("start")
        call_timed("stop")
        call_timed("reset")
        if i >= 3:  # warm-up
            samples.append(took)
    return summary(samples)


def demo_cell(client: Client, workdir: Path, idle: float) -> dict[str, object]:
    """The demo cell (config/demo_cell.yaml: 2 units, 7 EMs, the coordinator) in one process:
    idle CPU in Stopped, then in Execute (its simulated EMs cycling), and its RSS."""
    from packml_interfaces.srv import Command

    doc = yaml.safe_load(
        (Path(__file__).resolve().parents[1] / "config/demo_cell.yaml").read_text()
    )
    doc.pop("hmi", None)
    doc.pop("opcua", None)
    name = f"scale_demo_{os.getpid()}"
    cell = Launched(workdir, name, doc)
    try:
        time.sleep(SETTLE)
        entry: dict[str, object] = {"stopped_cpu_pct": idle_cpu(cell.proc.pid, idle)}
        service = client.node.create_client(Command, f"/{name}/coordinator/command")
        if not service.wait_for_service(timeout_sec=30):
            raise TimeoutError(f"{name}: coordinator command service not available")
        for command in (Command.Request.RESET, Command.Request.START):
            answer = call(service, Command.Request(command=command, source=BENCH_SOURCE))
            if not answer.accepted:
                raise RuntimeError(f"demo cell: {answer.message}")
        time.sleep(1)
        entry["execute_cpu_pct"] = idle_cpu(cell.proc.pid, idle)
        entry["rss_mb"] = rss_mb(cell.proc.pid)
        return entry
    finally:
        cell.stop()


def call(service, request, timeout: float = 30.0):  # type: ignore[no-untyped-def]
    """A service call, waited for (the bench's client spins in its own thread)."""
    import threading

    done = threading.Event()
    future = service.call_async(request)
    future.add_done_callback(lambda _: done.set())
    if not done.wait(timeout):
        raise TimeoutError(f"{service.srv_name}: no answer in {timeout} s")
    return future.result()


def summary(samples: list[float]) -> dict[str, float]:
    return {
        "p50_ms": round(statistics.median(samples) * 1e3, 3),
        "p99_ms": round(percentile(samples, 99) * 1e3, 3),
        "n": len(samples),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ems", default="1,8,32")
    parser.add_argument("--units", default="1,5,20")
    parser.add_argument("--idle", type=float, default=10.0, help="seconds of idle CPU measurement")
    parser.add_argument("--cycles", type=int, default=20)
    args = parser.parse_args()
    localhost_environment()
    os.environ["ROS_DOMAIN_ID"] = str(allocate_domain())
    from packml_interfaces.srv import Command

    commands = {"reset": Command.Request.RESET, "start": Command.Request.START,
                "stop": Command.Request.STOP}  # fmt: skip
    result: dict[str, object] = {"benchmark": "scale", "idle_seconds": args.idle}
    with tempfile.TemporaryDirectory(prefix="packml_scale_") as tmp:
        workdir = Path(tmp)
        client = Client()
        try:
            floor = subprocess.Popen([sys.executable, "-c", FLOOR])
            result["floor"] = at_rest(floor.pid, args.idle, settle=5.0)  # an empty node
            floor.send_signal(2)
            floor.wait(20)

            result["demo_cell"] = demo_cell(client, workdir, args.idle)

            by_ems: dict[str, object] = {}
            for n in [int(x) for x in args.ems.split(",")]:
                name = f"scale_ems{n}_{os.getpid()}"
                cell = Launched(workdir, name, ems_cell(n))
                try:
                    entry = at_rest(cell.proc.pid, args.idle)
                    topic = f"/{name}/unit/status"
                    client.watch(topic)
                    triggers = {c: client.trigger(f"/{name}/unit/{c}") for c in commands}
                    entry["unit_start"] = unit_latency(client, topic, triggers, args.cycles)
                    by_ems[str(n)] = entry
                finally:
                    cell.stop()
            result["one_unit_by_em_count"] = by_ems

            by_units: dict[str, object] = {}
            for n in [int(x) for x in args.units.split(",")]:
                name = f"scale_units{n}_{os.getpid()}"
                cell = Launched(workdir, name, units_cell(n))
                try:
                    entry = at_rest(cell.proc.pid, args.idle)
                    service = client.node.create_client(Command, f"/{name}/coordinator/command")
                    if not service.wait_for_service(timeout_sec=30):
                        raise TimeoutError(f"{name}: coordinator command service not available")

                    entry["cell_start"] = cell_latency(service, commands, args.cycles)
                    by_units[str(n)] = entry
                finally:
                    cell.stop()
            result["one_coordinator_by_unit_count"] = by_units
        finally:
            client.close()
    for key, per in (
        ("one_unit_by_em_count", "per_em"),
        ("one_coordinator_by_unit_count", "per_unit"),
    ):
        cases = result[key]
        if len(cases) >= 2:  # type: ignore[arg-type]
            counts = sorted(cases, key=int)  # type: ignore[arg-type]
            lo, hi = cases[counts[0]], cases[counts[-1]]  # type: ignore[index]
            added = int(counts[-1]) - int(counts[0])
            result[per] = {
                "idle_cpu_pct": round((hi["idle_cpu_pct"] - lo["idle_cpu_pct"]) / added, 3),
                "rss_mb": round((hi["rss_mb"] - lo["rss_mb"]) / added, 2),
            }
    result["load_average"] = os.getloadavg()
    json.dump(result, sys.stdout, indent=2)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
