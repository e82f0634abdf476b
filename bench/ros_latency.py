"""ROS latency benchmark: time from a ``start`` call in Idle until ``status`` shows Execute, and from
``stop`` until Stopped, with 0, 1, 4 and 8 EMs in separate processes; side by side with the rclpy
floor measured in the same run (a Trigger call whose handler publishes a Status, until that Status
arrives: one request hop plus one pub/sub hop) and the fan-out floor (the same message pattern with
trivial echo processes in place of the EMs: the Starting and the Execute message on one topic that
the echoes and the client read, as the unit's status is; beside it the floor of earlier runs, whose
last message went to the client only); 8 EMs composed in one process on one executor; 400
back-to-back reset / stop commands from one client, each sent when the previous one answered; RSS
of a unit and of an EM process. Prints JSON, with the ratios and the targets of issue 18.

    python bench/ros_latency.py [--cycles 200] [--ems 0,1,4,8] [--composed 8] [--back-to-back 400]

Everything stays on this machine (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST) in a domain of its own.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import yaml

from packml_ros2 import qos
from packml_ros2.testing.environment import allocate_domain, localhost_environment
from packml_ros2.testing.processes import Processes

FLOOR_SERVER = """
import sys, rclpy
from rclpy.node import Node
from std_srvs.srv import Trigger
from packml_interfaces.msg import Status
from packml_ros2 import qos, run
run.init()
node = Node("floor_server")
pub = node.create_publisher(Status, sys.argv[1] + "/status", qos.STATUS)
seq = [0]
def handle(req, resp):
    seq[0] += 1
    pub.publish(Status(unit="floor", sequence=seq[0], state_current=6, state_current_name="EXECUTE"))
    resp.success = True
    return resp
node.create_service(Trigger, sys.argv[1] + "/trigger", handle)
sys.exit(run.spin([node]))  # the executor the packml nodes use: a fair floor
"""


FANOUT_SERVER = """
import sys, rclpy
from rclpy.node import Node
from std_srvs.srv import Trigger
from packml_interfaces.msg import EmReport, Status
from packml_ros2 import qos, run
run.init()
n_echo, one_topic, ns = int(sys.argv[1]), sys.argv[2] == "one", sys.argv[3]
node = Node("fanout_server")
out = node.create_publisher(Status, ns + "/status", qos.STATUS)
# one topic: the Starting message and the Execute message on one topic that the echoes and the
# client read (the unit's status); else the Execute message on its own topic, to the client only
go = out if one_topic else node.create_publisher(Status, ns + "/go", qos.STATUS)
state = {"seq": 0, "replies": 0}
def handle(req, resp):
    state["seq"] += 1
    state["replies"] = 0
    go.publish(Status(unit="fanout", sequence=state["seq"], state_current=3))
    if n_echo == 0:
        out.publish(Status(unit="fanout", sequence=state["seq"], state_current=6))
    resp.success = True
    return resp
def on_reply(msg):
    if msg.sequence == state["seq"]:
        state["replies"] += 1
        if state["replies"] == n_echo:
            out.publish(Status(unit="fanout", sequence=state["seq"], state_current=6))
node.create_service(Trigger, ns + "/trigger", handle)
node.create_subscription(EmReport, ns + "/reports", on_reply, qos.EM_REPORTS)
sys.exit(run.spin([node]))
"""


ECHO = """
import sys, rclpy
from rclpy.node import Node
from packml_interfaces.msg import EmReport, Status
from packml_ros2 import qos, run
run.init()
node = Node("echo_" + sys.argv[1])
pub = node.create_publisher(EmReport, sys.argv[3] + "/reports", qos.EM_REPORTS)
def on_status(m):
    if m.state_current == 3:
        pub.publish(EmReport(em=sys.argv[1], kind=1, sequence=m.sequence))
node.create_subscription(Status, sys.argv[3] + sys.argv[2], on_status, qos.STATUS)
sys.exit(run.spin([node]))
"""


def percentile(values: list[float], p: float) -> float:
    ordered = sorted(values)
    k = (len(ordered) - 1) * p / 100
    lo, hi = int(k), min(int(k) + 1, len(ordered) - 1)
    return ordered[lo] + (ordered[hi] - ordered[lo]) * (k - lo)


def summary_ms(samples: list[float]) -> dict[str, float]:
    return {
        "p50_ms": round(statistics.median(samples) * 1e3, 3),
        "p99_ms": round(percentile(samples, 99) * 1e3, 3),
        "mean_ms": round(statistics.fmean(samples) * 1e3, 3),
        "n": len(samples),
    }


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return round(int(line.split()[1]) / 1024, 1)
    return 0.0


class Client:
    """The bench's rclpy side: Trigger clients and a status subscription with arrival times."""

    def __init__(self) -> None:
        import rclpy
        from packml_interfaces.msg import Status
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node

        from packml_ros2 import qos

        rclpy.init()
        self.node = Node("latency_bench")
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self._cond = threading.Condition()
        self._latest: dict[str, tuple[object, float]] = {}
        self._qos = qos.STATUS
        self._status_type = Status
        self._subs: dict[str, object] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        import rclpy

        while not self._stop.is_set() and rclpy.ok():
            self.executor.spin_once(timeout_sec=0.1)

    def watch(self, topic: str, msg_type: object = None) -> None:
        """Keep the latest message of ``topic`` (one subscription per topic: a second reader in
        this process would make every publisher of the topic write twice)."""
        with self._cond:
            self._latest.pop(topic, None)
        if topic in self._subs:
            return

        def on_status(msg: object, topic: str = topic) -> None:
            now = time.perf_counter()
            with self._cond:
                self._latest[topic] = (msg, now)
                self._cond.notify_all()

        self._subs[topic] = self.node.create_subscription(
            msg_type or self._status_type, topic, on_status, self._qos
        )

    def log(self, topic: str, msg_type: object) -> list[tuple[object, float]]:
        """Keep every message of ``topic`` with its arrival time (the list returned; clear it)."""
        arrivals: list[tuple[object, float]] = []

        def on_msg(msg: object) -> None:
            arrivals.append((msg, time.perf_counter()))

        self._subs[topic] = self.node.create_subscription(msg_type, topic, on_msg, qos.EM_REPORTS)
        return arrivals

    def wait(self, topic: str, predicate, timeout: float = 10.0) -> tuple[object, float]:  # type: ignore[no-untyped-def]
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                got = self._latest.get(topic)
                if got is not None and predicate(got[0]):
                    return got
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TimeoutError(
                        f"{topic}: condition not met in {timeout} s (last {got and got[0]})"
                    )
                self._cond.wait(remaining)

    def trigger(self, service: str):  # type: ignore[no-untyped-def]
        from std_srvs.srv import Trigger

        client = self.node.create_client(Trigger, service)
        if not client.wait_for_service(timeout_sec=15):
            raise TimeoutError(f"service {service} not available")
        return client

    @staticmethod
    def call(client) -> float:  # type: ignore[no-untyped-def]
        """Send the request; returns the time it was sent (the response is not waited for)."""
        from std_srvs.srv import Trigger

        t0 = time.perf_counter()
        client.call_async(Trigger.Request())
        return t0

    @staticmethod
    def call_wait(client, timeout: float = 10.0) -> float:  # type: ignore[no-untyped-def]
        """Send the request and wait for its response; returns the round trip in seconds."""
        from std_srvs.srv import Trigger

        done = threading.Event()
        t0 = time.perf_counter()
        future = client.call_async(Trigger.Request())
        future.add_done_callback(lambda _: done.set())
        if not done.wait(timeout):
            raise TimeoutError(f"no response in {timeout} s")
        return time.perf_counter() - t0

    def close(self) -> None:
        import rclpy

        self._stop.set()  # the spin thread ends before the context goes away
        self._thread.join(2)
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown()


class Pattern:
    """A message pattern set up and warmed up, measured one cycle at a time so that several are
    measured interleaved (each cycle of one next to a cycle of the others: the load of this
    shared machine, which drifts over seconds, weighs on all of them alike)."""

    def __init__(self, cycle, stop) -> None:  # type: ignore[no-untyped-def]
        self.cycle = cycle  #: one cycle; returns its samples (seconds)
        self.stop = stop
        self.samples: list[tuple[float, ...]] = []


def floor_pattern(client: Client, procs: Processes, ns: str) -> Pattern:
    """The rclpy floor: a Trigger call whose handler publishes a Status, until it arrives."""
    server = procs.start(f"floor_server{ns.replace('/', '_')}", "-c", FLOOR_SERVER, ns)
    topic = f"{ns}/status"
    client.watch(topic)
    trig = client.trigger(f"{ns}/trigger")
    sent = 0

    def cycle() -> tuple[float, ...]:
        nonlocal sent
        sent += 1
        t0 = client.call(trig)
        _, t1 = client.wait(topic, lambda m, n=sent: m.sequence == n)
        return (t1 - t0,)

    for _ in range(10):  # warm-up
        cycle()
    return Pattern(cycle, server.stop)


def fanout_pattern(
    client: Client, procs: Processes, ns: str, echoes: int, one_topic: bool = True
) -> Pattern:
    """The rclpy floor of the unit's message pattern with ``echoes`` EM processes: a Trigger
    call, one message to every echo process, one reply from each, one message back, on the topic
    the echo processes read too (as the unit's Execute status reaches its EMs and the client);
    ``one_topic=False``: the last message on a topic of its own, to the client only (the floor of
    earlier runs)."""
    pattern = "one" if one_topic else "two"
    tag = ns.replace("/", "_")
    server = procs.start(f"fanout_server{tag}", "-c", FANOUT_SERVER, str(echoes), pattern, ns)
    go = "/status" if one_topic else "/go"
    echo_procs = [procs.start(f"echo{tag}_{i}", "-c", ECHO, f"e{i}", go, ns) for i in range(echoes)]  # fmt: skip
    topic = f"{ns}/status"
    client.watch(topic)
    trig = client.trigger(f"{ns}/trigger")
    deadline = time.monotonic() + 30
    readers = echoes + 1 if one_topic else echoes
    while client.node.count_subscribers(ns + go) < readers and time.monotonic() < deadline:
        time.sleep(0.05)
    sent = 0

    def attempt(timeout: float) -> tuple[float, ...]:
        nonlocal sent
        sent += 1  # the server numbers the cycles as it gets the calls
        t0 = client.call(trig)
        _, t1 = client.wait(
            topic, lambda m, n=sent: m.sequence == n and m.state_current == 6, timeout
        )
        return (t1 - t0,)

    # Warm-up: 10 complete cycles. An echo's reply is lost while its writer has not matched the
    # server's reader yet (no API shows that from here): such a cycle is simply started again.
    warm, deadline = 0, time.monotonic() + 30
    while warm < 10:
        try:
            attempt(1.0)
            warm += 1
        except TimeoutError:
            if time.monotonic() > deadline:
                raise

    def stop() -> None:
        for proc in [*echo_procs, server]:
            proc.stop()

    return Pattern(lambda: attempt(10.0), stop)


def unit_pattern(
    client: Client, procs: Processes, workdir: Path, ems: int, composed: bool = False
) -> tuple[Pattern, dict[str, object]]:
    """A unit with ``ems`` EMs in a process each, or (``composed``) all in one process on one
    executor; a cycle is start -> Execute, stop -> Stopped, reset -> Idle and gives the first
    two. Also returns what the caller measures on it (cell, topic, triggers, processes)."""
    cell = f"bench{ems}{'c' if composed else ''}"
    em_names = [f"em{i}" for i in range(ems)]
    doc = {
        "cell": cell,
        "units": {
            "unit": {
                "persistence": {"path": str(workdir / f"{cell}.sqlite3")},
                "equipment_modules": {
                    n: {"sim": {"cycle_time": 0, "counter": "none", "lease": 2.0}} for n in em_names
                },
            }
        },
    }
    cell_file = workdir / f"{cell}.yaml"
    cell_file.write_text(yaml.safe_dump(doc))
    unit = procs.module(f"unit_{cell}", "packml_ros2.unit_node", str(cell_file), "unit")
    em_procs = (
        [procs.module(f"{cell}_ems", "packml_ros2.sim_em", str(cell_file), "unit", *em_names)]
        if composed
        else [
            procs.module(f"{cell}_{n}", "packml_ros2.sim_em", str(cell_file), "unit", n)
            for n in em_names
        ]
    )
    topic = f"/{cell}/unit/status"
    client.watch(topic)
    client.wait(topic, lambda m: sum(e.online for e in m.equipment_modules) == ems, 30)
    start, stop, reset = (
        client.trigger(f"/{cell}/unit/{name}") for name in ("start", "stop", "reset")
    )
    client.call(reset)
    client.wait(topic, lambda m: m.state_current_name == "IDLE")

    def cycle() -> tuple[float, ...]:
        t0 = client.call(start)
        _, t1 = client.wait(topic, lambda m: m.state_current_name == "EXECUTE")
        t2 = client.call(stop)
        _, t3 = client.wait(topic, lambda m: m.state_current_name == "STOPPED")
        client.call(reset)
        client.wait(topic, lambda m: m.state_current_name == "IDLE")
        return (t1 - t0, t3 - t2)

    for _ in range(10):  # warm-up
        cycle()

    def stop_all() -> None:
        for proc in [*em_procs, unit]:
            proc.stop()

    info = {"cell": cell, "topic": topic, "triggers": (start, stop, reset), "unit": unit,
            "ems": em_procs}  # fmt: skip
    return Pattern(cycle, stop_all), info


def interleave(patterns: list[Pattern], cycles: int) -> None:
    """``cycles`` cycles of each pattern, one of each in turn (the order rotated each round)."""
    for i in range(cycles):
        k = i % len(patterns)
        for pattern in patterns[k:] + patterns[:k]:
            pattern.samples.append(pattern.cycle())


def measure_em_count(
    client: Client, procs: Processes, workdir: Path, ems: int, cycles: int
) -> dict[str, object]:
    """The unit with ``ems`` EM processes beside its floors, measured interleaved (the ratios
    are those of the same minutes): the rclpy floor and the fan-out floor (one topic, as the
    unit's status); then, with EMs, the fan-out floor whose last message goes to the client only
    beside the unit again (one floor's processes at a time: each idle process adds DDS
    discovery traffic that every other one handles)."""
    floor = floor_pattern(client, procs, f"/bench_floor_{ems}")
    fan = fanout_pattern(client, procs, f"/bench_fanout_{ems}", ems)
    unit, info = unit_pattern(client, procs, workdir, ems)
    try:
        interleave([floor, fan, unit], cycles)
    finally:
        floor.stop()
        fan.stop()
    beside_floors, unit.samples = unit.samples, []
    unit_proc, em_procs = info["unit"], info["ems"]
    result: dict[str, object] = {
        "idle_to_execute": summary_ms([x[0] for x in beside_floors]),
        "stop_to_stopped": summary_ms([x[1] for x in beside_floors]),
        "floor": summary_ms([x[0] for x in floor.samples]),
        "fanout_floor": summary_ms([x[0] for x in fan.samples]),
        "unit_rss_mb": rss_mb(unit_proc.pid),  # type: ignore[attr-defined]
    }
    if ems:
        fan2 = fanout_pattern(client, procs, f"/bench_fanout2_{ems}", ems, one_topic=False)
        try:
            interleave([fan2, unit], cycles)
        finally:
            fan2.stop()
        two = summary_ms([x[0] for x in fan2.samples])
        result["fanout_floor_last_message_to_the_client_only"] = {
            **two, "unit_beside_it_p50_ms": summary_ms([x[0] for x in unit.samples])["p50_ms"]
        }  # fmt: skip
        result["em_rss_mb"] = rss_mb(em_procs[0].pid)  # type: ignore[index]
        result["hops_idle_to_execute"] = measure_hops(
            client,
            info["cell"],
            info["topic"],
            info["triggers"],
            max(cycles // 2, 10),  # type: ignore[arg-type]
        )
    unit.stop()
    return result


def measure_composed(
    client: Client, procs: Processes, workdir: Path, ems: int, cycles: int
) -> dict[str, object]:
    """The unit with ``ems`` EMs composed in one process (no floor beside it)."""
    unit, info = unit_pattern(client, procs, workdir, ems, composed=True)
    try:
        interleave([unit], cycles)
        rss = {"unit_rss_mb": rss_mb(info["unit"].pid), "em_rss_mb": rss_mb(info["ems"][0].pid)}  # type: ignore[attr-defined, index]
    finally:
        unit.stop()
    return {
        "idle_to_execute": summary_ms([x[0] for x in unit.samples]),
        "stop_to_stopped": summary_ms([x[1] for x in unit.samples]),
        **rss,
    }


def measure_hops(client: Client, cell: str, topic: str, triggers, cycles: int) -> dict[str, object]:  # type: ignore[no-untyped-def]
    """Where a ``start`` with EMs spends its time, from the EMs' State Complete reports seen by
    this client too (a separate pass: one more subscriber of the reports): the call until the
    first report of Starting (the command, the status to every EM, its reaction), until the last
    one (the spread of the EMs' replies), and from the last report until the unit's status shows
    Execute (the unit takes the reports and publishes)."""
    from packml_interfaces.msg import EmReport

    start, stop, reset = triggers
    reports = client.log(f"/{cell}/unit/em_reports", EmReport)
    first, spread, last = [], [], []
    for i in range(cycles + 3):
        reports.clear()
        t0 = client.call(start)
        _, t1 = client.wait(topic, lambda m: m.state_current_name == "EXECUTE")
        done = [
            t for m, t in list(reports) if m.kind == EmReport.KIND_STATE_COMPLETE and m.state == 3
        ]  # type: ignore[attr-defined]
        client.call(stop)
        client.wait(topic, lambda m: m.state_current_name == "STOPPED")
        client.call(reset)
        client.wait(topic, lambda m: m.state_current_name == "IDLE")
        if i >= 3 and done:
            first.append(min(done) - t0)
            spread.append(max(done) - min(done))
            last.append(t1 - max(done))
    return {"call_to_first_report": summary_ms(first), "first_to_last_report": summary_ms(spread),
            "last_report_to_execute_status": summary_ms(last)}  # fmt: skip


def measure_back_to_back(
    client: Client, procs: Processes, workdir: Path, commands: int
) -> dict[str, object]:
    """``commands`` reset / stop commands from one client, each sent when the previous one has
    answered, to a unit without EMs (persistence on, as in the demo cell): the time each takes to
    answer. A unit must sustain a command per millisecond without queueing."""
    cell = "b2b"
    doc = {
        "cell": cell,
        "units": {"unit": {"persistence": {"path": str(workdir / f"{cell}.sqlite3")}}},
    }
    cell_file = workdir / f"{cell}.yaml"
    cell_file.write_text(yaml.safe_dump(doc))
    unit = procs.module(f"unit_{cell}", "packml_ros2.unit_node", str(cell_file), "unit")
    topic = f"/{cell}/unit/status"
    client.watch(topic)
    client.wait(topic, lambda m: m.state_current_name == "STOPPED", 30)
    reset, stop = (client.trigger(f"/{cell}/unit/{name}") for name in ("reset", "stop"))
    for _ in range(5):  # warm-up
        client.call_wait(reset)
        client.call_wait(stop)
    samples = []
    t_all = time.perf_counter()
    for i in range(commands):
        samples.append(client.call_wait(reset if i % 2 == 0 else stop))
    wall = time.perf_counter() - t_all
    client.wait(topic, lambda m: m.state_current_name == "STOPPED", 10)
    rss = rss_mb(unit.pid)
    unit.stop()
    return {
        "commands": commands,
        "p50_ms": round(statistics.median(samples) * 1e3, 3),
        "p90_ms": round(percentile(samples, 90) * 1e3, 3),
        "p99_ms": round(percentile(samples, 99) * 1e3, 3),
        "max_ms": round(max(samples) * 1e3, 3),
        "commands_per_s": round(commands / wall, 1),
        "target_p90_ms<=10": percentile(samples, 90) <= 0.010,
        "unit_rss_mb": rss,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cycles", type=int, default=200)
    parser.add_argument("--ems", default="0,1,4,8")
    parser.add_argument("--composed", type=int, default=8, help="EMs in one process (0: none)")
    parser.add_argument("--back-to-back", type=int, default=400, help="commands (0: none)")
    args = parser.parse_args()
    localhost_environment()
    os.environ["ROS_DOMAIN_ID"] = str(allocate_domain())
    em_counts = [int(x) for x in args.ems.split(",")]

    with tempfile.TemporaryDirectory(prefix="packml_latency_") as tmp:
        workdir = Path(tmp)
        procs = Processes(workdir)
        client = Client()
        try:
            units = {
                str(n): measure_em_count(client, procs, workdir, n, args.cycles) for n in em_counts
            }
            composed = (
                measure_composed(client, procs, workdir, args.composed, args.cycles)
                if args.composed
                else None
            )
            b2b = (
                measure_back_to_back(client, procs, workdir, args.back_to_back)
                if args.back_to_back
                else None
            )
        finally:
            client.close()
            procs.close()
    result: dict[str, object] = {
        "benchmark": "ros_latency",
        "cycles": args.cycles,
        "units_by_em_count": units,
    }
    for data in units.values():
        p50 = data["idle_to_execute"]["p50_ms"]  # type: ignore[index]
        data["idle_to_execute_over_floor"] = round(p50 / data["floor"]["p50_ms"], 2)  # type: ignore[index]
        data["idle_to_execute_over_fanout_floor"] = round(p50 / data["fanout_floor"]["p50_ms"], 2)  # type: ignore[index]
        two = data.get("fanout_floor_last_message_to_the_client_only")
        if two is not None:
            beside = two["unit_beside_it_p50_ms"]  # type: ignore[index]
            data["idle_to_execute_over_fanout_floor_client_only"] = round(beside / two["p50_ms"], 2)  # type: ignore[index]
    if composed is not None:
        result["unit_with_composed_ems"] = {"ems_in_one_process": args.composed, **composed}
    if b2b is not None:
        result["back_to_back_reset_stop"] = b2b
    targets: dict[str, bool] = {}
    if "0" in units:
        targets["0_ems_p50<=2x_floor"] = units["0"]["idle_to_execute_over_floor"] <= 2.0  # type: ignore[index]
    if "8" in units:
        ex8 = units["8"]["idle_to_execute"]  # type: ignore[index]
        targets["8_ems_p50<=1.3x_fanout_floor"] = (
            units["8"]["idle_to_execute_over_fanout_floor"] <= 1.3  # type: ignore[index]
        )
        targets["8_ems_p99<=3x_p50"] = ex8["p99_ms"] <= 3 * ex8["p50_ms"]
    if b2b is not None:
        targets["back_to_back_p90_ms<=10"] = bool(b2b["target_p90_ms<=10"])
    result["targets"] = targets
    result["load_average"] = os.getloadavg()
    json.dump(result, sys.stdout, indent=2)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
