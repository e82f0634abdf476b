"""A plant, measured: N cells over several hosts in three discovery setups. Prints JSON.

    sudo .venv/bin/python bench/plant.py [--cells 20] [--hosts 5] [--window 60] [--rest 30] [--idle 20]
        [--setups simple,server,domains] [--processes] [--cycles 10] [--lease 3] [--em-lease 2]
        [--keep DIR]

Each cell is one unit with 8 simulated EMs (``--ems``), started by ``packml launch`` of a
generated cell file: in one process (the default), or with ``--processes`` one process per node
(meant for fewer cells). The cells are spread round-robin over ``--hosts`` network namespaces
acting as hosts, each joined by a veth pair to a bridge namespace the benchmark creates (and
removes at the end, also on Ctrl-C); an observer namespace holds the measuring client, and in the
``server`` setup a namespace of its own holds the Fast DDS Discovery Server. Nothing leaves these
namespaces: inside them DDS runs with ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET over UDPv4 only (shared
memory would bypass the links, and cutting one would change nothing).

The setups, side by side (each cell names its domain and server in its cell file's
``discovery:`` block):

- ``simple``: simple discovery (multicast), every cell in one domain;
- ``server``: a Fast DDS Discovery Server (``fastdds discovery``, in a namespace of its own); the
  cells' processes are its clients, the measuring client a super client (ROS_SUPER_CLIENT);
- ``domains``: simple discovery, one domain per cell (the measuring client joins each).

For each: the time from the launch until every unit is ready (its status seen by the measuring
client with every EM online); the traffic on the veths (bytes and packets, from the bridge
ports' counters) in the first ``--window`` seconds after the launch and then per minute at rest;
CPU (percent of one core, /proc/<pid>/stat) and RSS per cell and in total, at rest in Stopped (over
``--rest``, its traffic per minute) and in Execute (over ``--idle``); a line-wide reset and start of every unit (all
Trigger calls sent at once, until every unit's status shows the state) p50/p99 over ``--cycles``,
beside the floor measured in the same run: the same number of Trigger calls, sent at once by the
same client, to bare rclpy servers (one per host, in the setup's first domain) whose handler
publishes a Status, until every Status arrived; the time to detect one host cut off (its link down
-> every unit on it reported lost by DDS liveliness, packml_ros2.presence) and to see them all
again once it is back. The goals of issue 29 stand beside the figures (value / goal; where a goal
is missed, by how much). The goals are for 20 cells: at a smaller scale they only say how far off.

Needs root and iproute2 (network namespaces).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import signal
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from ros_latency import percentile, rss_mb
from scale import cpu_seconds

from packml_ros2.core.config import UnitConfig
from packml_ros2.testing.netns import Network, NsProcess, answer_requests, why_no_namespaces

REPO = Path(__file__).resolve().parents[1]
SUBNET = "10.214.0"
DS_PORT = 11811
SETUPS = ("simple", "server", "domains")
#: the goals of issue 29 (20 cells on this machine's 2 cores)
GOALS = {
    "ready_s": 30.0,  # every unit ready, with the discovery server
    "rest_cpu_pct_per_cell": 2.0,  # at rest, percent of one core per cell
    "rest_rss_total_mb": 3 * 1024.0,  # at rest, every cell's RSS together
    "line_start_p50_ratio": 1.5,  # a line-wide start p50 against its bare-client floor
    "cut_detect_over_lease_s": 0.5,  # a host cut detected within the lease + this
}

FLOOR_SERVER = """
import sys
from rclpy.node import Node
from std_srvs.srv import Trigger
from packml_interfaces.msg import Status
from packml_ros2 import qos, run
run.init()
node = Node("plant_floor")
seqs = {}
def serve(ns):
    pub = node.create_publisher(Status, ns + "/status", qos.STATUS)
    seqs[ns] = 0
    def handle(req, resp):
        seqs[ns] += 1
        pub.publish(Status(unit="floor", sequence=seqs[ns], state_current_name="EXECUTE"))
        resp.success = True
        return resp
    node.create_service(Trigger, ns + "/trigger", handle)
for ns in sys.argv[1:]:
    serve(ns)
sys.exit(run.spin([node]))
"""


# ====================================================================================================
# Network namespaces
# ====================================================================================================
def traffic(before: dict[str, dict[str, int]], after: dict[str, dict[str, int]],
            seconds: float) -> dict[str, Any]:  # fmt: skip
    """The traffic between two counter readings: in total (what the hosts sent, what the links
    delivered) and per host, and the total sent per minute."""
    per_host = {h: {k: after[h][k] - before[h][k] for k in after[h]} for h in after}
    total = {k: sum(v[k] for v in per_host.values()) for k in next(iter(per_host.values()))}
    return {
        "seconds": round(seconds, 2),
        **total,
        "sent_bytes_per_min": round(total["sent_bytes"] * 60 / seconds),
        "sent_packets_per_min": round(total["sent_packets"] * 60 / seconds),
        "per_host": per_host,
    }


# ====================================================================================================
# Processes inside namespaces
# ====================================================================================================
def ns_environment(domain: int, setup: str, server: str, super_client: bool = False) -> dict[str, str]:  # fmt: skip
    """The environment of a process in a namespace: the namespaces' subnet is all there is, UDPv4
    only, the quick-discovery profile (not the loopback one)."""
    from packml_ros2.paths import fastdds_profile

    env = dict(os.environ)
    for key in ("ROS_DISCOVERY_SERVER", "ROS_SUPER_CLIENT", "ROS_STATIC_PEERS"):
        env.pop(key, None)
    env.update(
        ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET",
        FASTDDS_BUILTIN_TRANSPORTS="UDPv4",
        FASTDDS_DEFAULT_PROFILES_FILE=str(fastdds_profile("SUBNET")),
        ROS_DOMAIN_ID=str(domain),
        PYTHONUNBUFFERED="1",
        PYTHONPATH=os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH", "")) if p),
    )
    if setup == "server":
        env["ROS_DISCOVERY_SERVER"] = f"{server}:{DS_PORT}"
        if super_client:
            env["ROS_SUPER_CLIENT"] = "TRUE"
    return env


#: s the observer has to answer a line-wide call (its own limit is 60 s, plus the discovery of
#: every unit's services before the first call)
ANSWER_WAIT = 130.0


class Observer(NsProcess):
    """The measuring client (this file run as ``observe``): one JSON request per line on its
    stdin, one JSON answer per line on its stdout."""

    def __init__(self, net: Network, env: dict[str, str], log_dir: Path) -> None:
        cmd = [sys.executable, str(Path(__file__).resolve()), "observe"]
        super().__init__(net, "obs", "observer", cmd, env, log_dir, pipe=True, cwd=REPO)


# ====================================================================================================
# The plant
# ====================================================================================================
def cell_doc(name: str, ems: int, lease: float, workdir: Path,
             discovery: dict[str, Any], em_lease: float) -> dict[str, Any]:  # fmt: skip
    """A cell of one unit with ``ems`` simulated EMs; ``discovery``: its discovery block (the
    domain, the server), as an integrator names it."""
    sim = {"cycle_time": 0.5, "counter": "processed", "lease": em_lease}
    return {
        "cell": name,
        "discovery": discovery,
        "units": {
            "unit": {
                "em_lease": em_lease,
                "equipment_modules": {f"em{i}": {"sim": sim} for i in range(ems)},
                "persistence": {"path": str(workdir / f"{name}.sqlite3")},
            }
        },
        "coordinator": {"enabled": False, "unit_lease": lease},
    }


def summary_ms(samples: list[float]) -> dict[str, float]:
    out: dict[str, float] = {
        "p50_ms": round(statistics.median(samples) * 1e3, 2),
        "p99_ms": round(percentile(samples, 99) * 1e3, 2),
        "n": len(samples),
    }
    return out


def goal(value: float | None, target: float, higher_is_better: bool = False) -> dict[str, Any]:
    """A figure beside its goal: value / goal, met, and by how much it is missed."""
    if value is None:
        return {"goal": target, "value": None, "met": False, "missed_by": "not measured"}
    met = value >= target if higher_is_better else value <= target
    entry: dict[str, Any] = {"goal": target, "value": round(value, 3),
                             "ratio_to_goal": round(value / target, 3), "met": met}  # fmt: skip
    if not met:
        entry["missed_by"] = round(abs(value - target), 3)
    return entry


class Plant:
    """One setup: the cells, the floor servers and the observer, started and measured."""

    def __init__(self, args: argparse.Namespace, net: Network, setup: str, domains: list[int],
                 workdir: Path) -> None:  # fmt: skip
        self.args, self.net, self.setup = args, net, setup
        self.workdir = workdir / setup
        self.workdir.mkdir()
        self.hosts = [h for h in net.ns if h.startswith("h")]
        self.cells = [f"c{i}" for i in range(args.cells)]
        self.host_of = {c: self.hosts[i % len(self.hosts)] for i, c in enumerate(self.cells)}
        self.domain_of = {c: domains[1 + i] if setup == "domains" else domains[0]
                          for i, c in enumerate(self.cells)}  # fmt: skip
        self.base = domains[0]
        self.server = net.address.get("ds", "")
        self.procs: list[NsProcess] = []
        self.cell_procs: dict[str, NsProcess] = {}
        self.observer: Observer | None = None

    def env(self, domain: int, super_client: bool = False) -> dict[str, str]:
        return ns_environment(domain, self.setup, self.server, super_client)

    def start(self) -> tuple[float, dict[str, dict[str, int]]]:
        """The discovery server (``server``), the observer and the floor servers; then every cell
        at once. Returns the monotonic time of the cells' launch and the links' counters then."""
        if self.setup == "server":
            self.start_discovery_server()
        self.observer = Observer(self.net, self.env(self.base, super_client=True), self.workdir)
        self.procs.append(self.observer)
        units = {f"/{c}/unit": self.domain_of[c] for c in self.cells}
        floors = [f"/floor/{c}" for c in self.cells]
        self.observer.ask("watch", units=units, floors=floors, floor_domain=self.base,
                          lease=self.args.lease)  # fmt: skip
        for host in self.hosts:
            mine = [f"/floor/{c}" for c in self.cells if self.host_of[c] == host]
            if mine:
                cmd = [sys.executable, "-c", FLOOR_SERVER, *mine]
                self.procs.append(NsProcess(self.net, host, f"floor_{host}", cmd,
                                              self.env(self.base), self.workdir, cwd=REPO))  # fmt: skip
        launched, counters = time.monotonic(), self.net.counters()
        for c in self.cells:
            path = self.workdir / f"{c}.yaml"
            discovery: dict[str, Any] = {"domain": self.domain_of[c]}
            if self.setup == "server":
                discovery["server"] = f"{self.server}:{DS_PORT}"
            doc = cell_doc(c, self.args.ems, self.args.lease, self.workdir, discovery,
                           self.args.em_lease)  # fmt: skip
            path.write_text(yaml.safe_dump(doc, sort_keys=False))
            cmd = [sys.executable, "-m", "packml_ros2.cli.main", "launch", str(path)]
            if self.args.processes:
                cmd += ["--processes"]
            # the cell's domain and server come from its cell file, as they would on a plant
            env = self.env(self.domain_of[c])
            for key in ("ROS_DOMAIN_ID", "ROS_DISCOVERY_SERVER"):
                env.pop(key, None)
            proc = NsProcess(self.net, self.host_of[c], c, cmd, env, self.workdir, cwd=REPO)
            self.procs.append(proc)
            self.cell_procs[c] = proc
        return launched, counters

    def start_discovery_server(self, timeout: float = 15.0) -> None:
        """Fast DDS's tool (as ``packml launch`` hosts it), in its namespace, until it says it
        runs: the plant's infrastructure is up before the cells start."""
        from packml_ros2.discovery_server import STARTED, server_command

        argv, tool_env = server_command(self.server, DS_PORT)
        env = {**self.env(self.base), "LD_LIBRARY_PATH": tool_env.get("LD_LIBRARY_PATH", "")}
        server = NsProcess(self.net, "ds", "discovery_server", argv, env, self.workdir, cwd=REPO)
        self.procs.append(server)
        deadline = time.monotonic() + timeout
        while STARTED.decode() not in server.output():
            if not server.running() or time.monotonic() > deadline:
                raise RuntimeError(
                    f"the discovery server did not start:\n{server.output()[-1000:]}"
                )
            time.sleep(0.05)

    def dead(self) -> list[str]:
        return [p.name for p in self.procs if p.popen.poll() is not None]

    def wait_ready(self, launched: float, before: dict[str, dict[str, int]],
                   timeout: float) -> tuple[list[float], dict[str, Any]]:  # fmt: skip
        """Until every unit is ready: the seconds each took from the launch, in order; the traffic
        of the first window is read on the way."""
        assert self.observer is not None
        first = None
        deadline = launched + timeout
        ready_at: list[float] | None = None
        while True:
            now = time.monotonic()
            if first is None and now >= launched + self.args.window:
                first = traffic(before, self.net.counters(), now - launched)
            if ready_at is None:
                times = self.observer.ask("ready")
                if all(t is not None for t in times.values()):
                    ready_at = sorted(t - launched for t in times.values())
            if ready_at is not None and first is not None:
                return ready_at, first
            if now > deadline:
                times = self.observer.ask("ready")
                late = [c for c in self.cells if times.get(f"/{c}/unit") is None]
                tails = "\n".join(f"-- {c} on {self.host_of[c]}:\n"
                                  + self.cell_procs[c].output()[-600:] for c in late[:3])  # fmt: skip
                raise TimeoutError(f"{self.setup}: not every unit ready in {timeout:g} s: "
                                   f"not ready: {', '.join(late)}\n{tails}")  # fmt: skip
            if self.dead():
                raise RuntimeError(f"{self.setup}: exited: {self.dead()}\n"
                                   + self.cell_procs[self.cells[0]].output()[-2000:])  # fmt: skip
            time.sleep(0.1)

    def at_rest(self, seconds: float) -> dict[str, Any]:
        """CPU (percent of one core over ``seconds``) and RSS per cell and in total, the same of
        the discovery server (``server``), and the traffic meanwhile."""
        pids = {c: p.pids() for c, p in self.cell_procs.items()}
        pids.update({p.name: p.pids() for p in self.procs if p.name == "discovery_server"})
        t0, c0 = time.monotonic(), self.net.counters()
        cpu0 = {c: sum(_cpu(p) for p in ps) for c, ps in pids.items()}
        time.sleep(seconds)  # the measurement window
        t1 = time.monotonic()
        cpu1 = {c: sum(_cpu(p) for p in ps) for c, ps in pids.items()}
        net = traffic(c0, self.net.counters(), t1 - t0)
        cpu = {c: round((cpu1[c] - cpu0[c]) / (t1 - t0) * 100, 2) for c in pids}
        rss = {c: round(sum(_rss(p) for p in ps), 1) for c, ps in pids.items()}
        server = {"cpu_pct": cpu.pop("discovery_server", 0.0),
                  "rss_mb": rss.pop("discovery_server", 0.0)}  # fmt: skip
        out = {
            "cpu_pct_total": round(sum(cpu.values()), 2),
            "cpu_pct_per_cell_mean": round(statistics.fmean(cpu.values()), 2),
            "cpu_pct_per_cell_max": max(cpu.values()),
            "rss_mb_total": round(sum(rss.values()), 1),
            "rss_mb_per_cell_mean": round(statistics.fmean(rss.values()), 1),
            "cpu_pct_per_cell": cpu,
            "rss_mb_per_cell": rss,
            "processes": sum(len(pids[c]) for c in cpu),
            "traffic": net,
        }
        if "discovery_server" in pids:
            out["discovery_server"] = server
        return out

    def line(self) -> dict[str, Any]:
        """``--cycles`` line-wide reset and start (and stop between), each beside a floor call
        of the same width; the line is left in Execute."""
        assert self.observer is not None
        samples: dict[str, list[float]] = {"reset": [], "start": [], "floor": []}
        warmup = 1
        for i in range(self.args.cycles + warmup):
            for verb, state in (("reset", "IDLE"), ("start", "EXECUTE")):
                took = self.observer.ask("line", ANSWER_WAIT, verb=verb, state=state)
                floor = self.observer.ask("floor", ANSWER_WAIT)
                if i >= warmup:
                    samples[verb].append(took)
                    samples["floor"].append(floor)
            if i < self.args.cycles + warmup - 1:
                self.observer.ask("line", ANSWER_WAIT, verb="stop", state="STOPPED")
        out = {k: summary_ms(v) for k, v in samples.items()}
        for verb in ("reset", "start"):
            out[f"{verb}_p50_over_floor"] = round(out[verb]["p50_ms"] / out["floor"]["p50_ms"], 2)
        return out

    def cut(self) -> dict[str, Any]:
        """Cut the first host off, until every unit on it is reported lost; restore it, until
        every one is seen again (and its status with every EM online arrives)."""
        assert self.observer is not None
        host = self.hosts[0]
        units = [f"/{c}/unit" for c in self.cells if self.host_of[c] == host]
        lease = self.args.lease
        cut_at = time.monotonic()
        self.net.cut(host)
        lost = self.observer.ask("presence_wait", lease * 4 + 10, units=units, present=False,
                                 within=lease * 4 + 5)  # fmt: skip
        restore_at = time.monotonic()
        self.net.restore(host)
        back = self.observer.ask("presence_wait", 70, units=units, present=True, within=60)
        detected = None if lost is None else lost["at"] - cut_at
        recovered = None if back is None else back["at"] - restore_at
        return {
            "host": host,
            "units": len(units),
            "lease_s": lease,
            "detect_s": None if detected is None else round(detected, 3),
            "recover_s": None if recovered is None else round(recovered, 3),
            "recovered": back is not None,
            "lost_because": None if lost is None else lost["reasons"],
            "note": "counted from the cut; DDS counts the lease from the units' last liveliness "
            "assertion, which came before the cut by up to its assertion period: detect_s lies "
            "between the lease less that period and the lease",
        }

    def stop(self) -> list[str]:
        """Cells first (all told at once, then waited for), then the floor servers, the observer
        and the discovery server."""
        failures = []
        for proc in self.cell_procs.values():
            if proc.running():
                proc.popen.send_signal(signal.SIGINT)
        rank = {"observer": 2, "discovery_server": 3}
        for proc in sorted(
            self.procs, key=lambda p: rank.get(p.name, 1 if "floor" in p.name else 0)
        ):
            code = proc.stop(20)
            if code not in (0, -signal.SIGINT, -signal.SIGKILL, 130):
                failures.append(f"{proc.name} exited {code}: {proc.output()[-500:]}")
        return failures


def _cpu(pid: int) -> float:
    try:
        return cpu_seconds(pid)
    except OSError:
        return 0.0


def _rss(pid: int) -> float:
    try:
        return rss_mb(pid)
    except OSError:
        return 0.0


def run_setup(args: argparse.Namespace, net: Network, setup: str, domains: list[int],
              workdir: Path) -> dict[str, Any]:  # fmt: skip
    plant = Plant(args, net, setup, domains, workdir)
    result: dict[str, Any] = {"setup": setup}
    stage = "start"
    try:
        launched, counters = plant.start()
        stage = "ready"
        ready, result["traffic_first_window"] = plant.wait_ready(
            launched, counters, args.ready_timeout
        )
        result["ready_s"] = round(ready[-1], 3)  # the last unit
        # the spread: a slow start of every cell, or a few cells that discover late
        result["ready_spread_s"] = {"first": round(ready[0], 3),
                                    "median": round(statistics.median(ready), 3)}  # fmt: skip
        stage = "rest_stopped"
        result["rest_stopped"] = plant.at_rest(args.rest)
        stage = "line"
        result["line"] = plant.line()
        stage = "rest_execute"
        result["rest_execute"] = plant.at_rest(args.idle)
        stage = "host_cut"
        result["host_cut"] = plant.cut()
    except (TimeoutError, RuntimeError) as exc:  # what was measured stays, beside where it stopped
        result["error"] = f"at {stage}: {exc}"[:4000]
    finally:
        failures = plant.stop()
        if failures:
            result["exit_failures"] = failures
    result["goals"] = goals(result, args)
    return result


def goals(r: dict[str, Any], args: argparse.Namespace) -> dict[str, Any]:
    rest = [r[k] for k in ("rest_stopped", "rest_execute") if k in r]
    cut = r.get("host_cut", {})
    return {
        "ready_s": goal(r.get("ready_s"), GOALS["ready_s"]),
        "rest_cpu_pct_per_cell": goal(
            max((x["cpu_pct_per_cell_mean"] for x in rest), default=None),
            GOALS["rest_cpu_pct_per_cell"],
        ),
        "rest_rss_total_mb": goal(
            max((x["rss_mb_total"] for x in rest), default=None), GOALS["rest_rss_total_mb"]
        ),
        "line_start_p50_ratio": goal(
            r.get("line", {}).get("start_p50_over_floor"), GOALS["line_start_p50_ratio"]
        ),
        "cut_detect_s": goal(cut.get("detect_s"), args.lease + GOALS["cut_detect_over_lease_s"]),
        "recovered_without_a_hand": {
            "goal": True,
            "value": cut.get("recovered", False),
            "met": bool(cut.get("recovered")),
        },
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, default=20)
    parser.add_argument("--hosts", type=int, default=5, help="network namespaces holding cells")
    parser.add_argument("--ems", type=int, default=8, help="simulated EMs per cell")
    parser.add_argument("--processes", action="store_true", help="one process per node")
    parser.add_argument("--setups", default=",".join(SETUPS))
    parser.add_argument("--window", type=float, default=60.0,
                        help="s: the first traffic window after the launch")  # fmt: skip
    parser.add_argument("--rest", type=float, default=30.0,
                        help="s: the rest in Stopped (CPU, traffic per minute)")  # fmt: skip
    parser.add_argument("--idle", type=float, default=20.0, help="s: the rest in Execute")
    parser.add_argument("--cycles", type=int, default=10, help="line-wide reset/start cycles")
    parser.add_argument("--lease", type=float, default=3.0, help="s: the units' unit_lease")
    parser.add_argument("--em-lease", type=float, default=UnitConfig.em_lease,
                        help="s: the EMs' lease (their heartbeats: 4 reports and 10 beats a lease)")  # fmt: skip
    parser.add_argument("--ready-timeout", type=float, default=180.0)
    parser.add_argument("--keep", type=Path, default=None,
                        help="a directory to copy every process's log and cell file into")  # fmt: skip
    args = parser.parse_args()
    setups = [s.strip() for s in args.setups.split(",") if s.strip()]
    unknown = sorted(set(setups) - set(SETUPS))
    if unknown or args.cells < 1 or args.hosts < 1:
        parser.error(f"unknown setup(s) {unknown}; choose from {', '.join(SETUPS)}" if unknown
                     else "--cells and --hosts must be at least 1")  # fmt: skip
    reason = why_no_namespaces()
    if reason:
        print(f"plant: {reason}", file=sys.stderr)
        return 2
    from packml_ros2.testing.environment import allocate_domain

    # inside the namespaces nothing else is there: the domains are locked only to keep the machine's
    # own runs (allocate_domain) predictable
    domains = [allocate_domain() for _ in range(1 + (args.cells if "domains" in setups else 0))]
    net = Network([f"h{i}" for i in range(args.hosts)] + ["obs", "ds"], SUBNET, prefix="pl")

    def on_term(signum: int, _: Any) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, on_term)
    signal.signal(signal.SIGINT, signal.default_int_handler)  # also where it was ignored (nohup, &)
    result: dict[str, Any] = {
        "benchmark": "plant",
        "cells": args.cells,
        "hosts": args.hosts,
        "ems_per_cell": args.ems,
        "nodes": args.cells * (1 + args.ems),
        "processes_per_node": args.processes,
        "window_s": args.window,
        "rest_s": args.rest,
        "idle_s": args.idle,
        "em_lease_s": args.em_lease,
        "goals_for_20_cells": GOALS,
        # CPU figures grow with the machine's load (other work on the same cores): beside them
        "load_average_at_start": os.getloadavg(),
        "setups": {},
    }
    try:
        with tempfile.TemporaryDirectory(prefix="packml_plant_") as tmp:
            net.setup()
            for setup in setups:
                try:
                    result["setups"][setup] = run_setup(args, net, setup, domains, Path(tmp))
                except (RuntimeError, TimeoutError) as exc:
                    result["setups"][setup] = {"setup": setup, "error": str(exc)[-3000:]}
            if args.keep is not None:
                shutil.copytree(tmp, args.keep, dirs_exist_ok=True)
    except KeyboardInterrupt:
        print(
            "plant: interrupted; its processes are stopped, its namespaces removed", file=sys.stderr
        )
        return 130
    finally:
        problems = net.teardown()
        if problems:
            print("\n".join(problems), file=sys.stderr)
    result["table"] = table(result["setups"])
    result["load_average_at_end"] = os.getloadavg()
    json.dump(result, sys.stdout, indent=2)
    print()
    print("\n".join(result["table"]), file=sys.stderr)
    return 0 if all("error" not in s for s in result["setups"].values()) else 1


def table(setups: dict[str, dict[str, Any]]) -> list[str]:
    """The setups side by side, one line each (stderr, for people)."""
    head = f"{'setup':<8} {'ready s':>8} {'first-window kB':>15} {'rest kB/min':>11} " \
           f"{'cpu %/cell':>10} {'rss MB':>8} {'start p50 ms':>12} {'floor ms':>9} " \
           f"{'cut s':>6} {'back s':>7}"  # fmt: skip
    lines = [head]
    for name, s in setups.items():
        if "error" in s:  # (what was measured before it, on its own line below)
            lines.append(f"{name:<8} error {s['error'].splitlines()[0][:100]}")

        def get(*keys: str, s: dict[str, Any] = s) -> Any:
            v: Any = s
            for k in keys:
                v = v.get(k) if isinstance(v, dict) else None
            return "-" if v is None else v

        first = get("traffic_first_window", "sent_bytes")
        rest = get("rest_stopped", "traffic", "sent_bytes_per_min")
        lines.append(
            f"{name:<8} {get('ready_s'):>8} {first if first == '-' else round(first / 1e3):>15} "
            f"{rest if rest == '-' else round(rest / 1e3):>11} "
            f"{get('rest_stopped', 'cpu_pct_per_cell_mean'):>10} "
            f"{get('rest_stopped', 'rss_mb_total'):>8} {get('line', 'start', 'p50_ms'):>12} "
            f"{get('line', 'floor', 'p50_ms'):>9} {get('host_cut', 'detect_s'):>6} "
            f"{get('host_cut', 'recover_s'):>7}"
        )
    return lines


# ====================================================================================================
# The observer (runs in the "obs" namespace)
# ====================================================================================================
class Domain:
    """A context, a node and its executor thread in one ROS domain (also bench/line.py's)."""

    def __init__(self, domain: int, name: str = "plant_observer") -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node

        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.node = Node(f"{name}_{os.getpid()}_{domain}", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        from rclpy.executors import ExternalShutdownException, ShutdownException

        with contextlib.suppress(ExternalShutdownException, ShutdownException):
            self.executor.spin()

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=2)
        self.node.destroy_node()
        self.context.try_shutdown()
        self.thread.join(2)


class _Watch:
    """What the observer follows: the units' status, presence and Trigger services, the floor."""

    def __init__(self, units: dict[str, int], floors: list[str], floor_domain: int,
                 lease: float) -> None:  # fmt: skip
        from packml_interfaces.msg import Status
        from std_srvs.srv import Trigger

        from packml_ros2 import qos
        from packml_ros2.presence import Presence

        self.cond = threading.Condition()
        self.latest: dict[str, Any] = {}
        self.ready: dict[str, float | None] = dict.fromkeys(units)
        self.present: dict[str, tuple[bool | None, float, str]] = {}
        self.domains: dict[int, Domain] = {}
        self.clients: dict[tuple[str, str], Any] = {}
        self.units, self.floors = units, floors
        for d in sorted({*units.values(), floor_domain}):
            self.domains[d] = Domain(d)

        def on_status(msg: Any, path: str) -> None:
            with self.cond:
                self.latest[path] = msg
                ems = msg.equipment_modules
                if self.ready.get(path, 0) is None and ems and all(e.online for e in ems):
                    self.ready[path] = time.monotonic()
                self.cond.notify_all()

        def on_presence(path: str, seen: Any) -> None:
            with self.cond:
                self.present[path] = (seen.present, time.monotonic(), seen.reason)
                self.cond.notify_all()

        self.presence = []
        by_domain: dict[int, list[str]] = {}
        for path, d in units.items():
            by_domain.setdefault(d, []).append(path)
        for d, paths in by_domain.items():
            node = self.domains[d].node
            for path in paths:
                node.create_subscription(Status, f"{path}/status",
                                         lambda m, p=path: on_status(m, p), qos.STATUS)  # fmt: skip
                for verb in ("reset", "start", "stop"):
                    self.clients[(path, verb)] = node.create_client(Trigger, f"{path}/{verb}")
            self.presence.append(Presence(node, paths, lease, on_change=on_presence))
        node = self.domains[floor_domain].node
        for path in floors:
            node.create_subscription(Status, f"{path}/status",
                                     lambda m, p=path: on_status(m, p), qos.STATUS)  # fmt: skip
            self.clients[(path, "trigger")] = node.create_client(Trigger, f"{path}/trigger")

    def calls(self, paths: list[str], verb: str, done: Any, timeout: float) -> float:
        """Send ``verb`` to every path at once; wait until every answer came and ``done()``
        holds; the seconds from the first send."""
        from std_srvs.srv import Trigger

        for path in paths:
            if not self.clients[(path, verb)].wait_for_service(timeout_sec=timeout):
                raise TimeoutError(f"{path}/{verb} not available")
        answers: list[Any] = []

        def on_answer(future: Any) -> None:
            with self.cond:
                answers.append(future.result())
                self.cond.notify_all()

        t0 = time.monotonic()
        for path in paths:
            self.clients[(path, verb)].call_async(Trigger.Request()).add_done_callback(on_answer)
        deadline = t0 + timeout
        with self.cond:
            while not (len(answers) == len(paths) and done()):
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(
                        f"{verb}: {len(answers)}/{len(paths)} answers in {timeout:g} s"
                    )
                self.cond.wait(left)
            took = time.monotonic() - t0
        refused = [a.message for a in answers if not a.success]
        if refused:
            raise RuntimeError(f"{verb} refused: {refused[:3]}")
        return took

    def line(self, verb: str, state: str, timeout: float = 60.0) -> float:
        paths = list(self.units)
        return self.calls(paths, verb, lambda: all(
            self.latest.get(p) is not None and self.latest[p].state_current_name == state
            for p in paths), timeout)  # fmt: skip

    def floor(self, timeout: float = 60.0) -> float:
        with self.cond:
            before = {p: self.latest[p].sequence if p in self.latest else 0 for p in self.floors}
        return self.calls(self.floors, "trigger", lambda: all(
            p in self.latest and self.latest[p].sequence > before[p] for p in self.floors),
            timeout)  # fmt: skip

    def presence_wait(
        self, units: list[str], present: bool, within: float
    ) -> dict[str, Any] | None:
        """The monotonic time at which the last of ``units`` got to ``present`` and why (None: not in
        ``within`` s); for ``present``, also its status with every EM online."""
        deadline = time.monotonic() + within

        def there() -> bool:
            if not all(self.present.get(u, (None, 0.0, ""))[0] is present for u in units):
                return False
            return not present or all(
                u in self.latest and all(e.online for e in self.latest[u].equipment_modules)
                for u in units
            )

        with self.cond:
            while not there():
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self.cond.wait(left)
            return {"at": max(self.present[u][1] for u in units),
                    "reasons": sorted({self.present[u][2] for u in units} - {""})}  # fmt: skip

    def ready_times(self) -> dict[str, float | None]:
        """When each unit was first seen ready (monotonic; None: not yet)."""
        with self.cond:
            return dict(self.ready)

    def close(self) -> None:
        for d in self.domains.values():
            d.close()


def observe() -> int:
    from packml_ros2 import run

    run.default_environment()
    watch: list[_Watch] = []
    ops: dict[str, Any] = {}

    def start(units: dict[str, int], floors: list[str], floor_domain: int, lease: float) -> bool:
        w = _Watch(units, floors, floor_domain, lease)
        watch.append(w)
        ops.update(ready=w.ready_times, line=w.line, floor=w.floor, presence_wait=w.presence_wait)
        return True

    ops["watch"] = start
    try:
        answer_requests(ops)
    finally:
        for w in watch:
            w.close()
    return 0


if __name__ == "__main__":
    if sys.argv[1:2] == ["observe"]:
        sys.exit(observe())
    sys.exit(main())
