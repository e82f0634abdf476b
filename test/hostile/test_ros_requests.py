"""Issue 15: thousands of seeded hostile requests against a running unit node over real DDS: every
mutating service from remote sources while the remote lock holds, sources outside the grammar,
strings and arrays past their bounds, control characters, numbers out of range; pipelined 200 at
a time by one client (none may be lost: services keep 256); and forged EM reports (made-up EMs,
fields out of range, another writer's State Complete for the configured EM).

Every request is answered, refused with its reason code and a printable sentence; nothing of the
unit changes (no status message, no transition, the same EMs); the process's memory and its log
stay bounded (figures below)."""

from __future__ import annotations

import math
import os
import random
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest
import rclpy
from packml_interfaces.msg import Descriptor, EmReport, Product, Result, TransitionEvent, UnitInput
from packml_interfaces.srv import (
    AckAlarms,
    Command,
    ResetAlarms,
    ResetCounters,
    ResetTimes,
    SetAlarm,
    SetEmActive,
    SetInterlock,
    SetMachSpeed,
    SetMode,
    SetProduct,
    SetRemoteCommands,
    SetUnitParameters,
)

from packml_ros2 import qos
from packml_ros2.core.limits import MAX_REQUEST_TEXT
from test.ros.test_unit_services import FakeEm, make_unit, wait_until

__all__ = ["make_unit"]  # the fixture

pytestmark = pytest.mark.ros

SEED = 1515
COUNT = 6000  # ~15 s here (2.5 ms a request, answers included)
BATCH = 200  # pipelined by one client before the first answer is read
REPORTS = 1000
WARM_UP = 400
MAX_RSS_GROWTH_MB = 40
MAX_LOG_BYTES = 200_000  # every refusal is logged escaped and rate-limited
R = Result

UNIT_DOC: dict[str, Any] = {
    "mach_design_speed": 50,
    "alarms": [{"id": 1, "message": "E-stop", "category": 0}],
    "equipment_modules": {"nozzle": {}},
}

LOCAL = ("", "operator", "operator:alice")
REMOTE = ("hmi:op", "opcua:scada", "remote:mes", "remote", "coordinator", "hmi:anyone")
BAD_SOURCES = ("REMOTE:x", " remote:x", "Remote:x", "remote_hmi", "em:nozzle", "unit", "hmi:a b",
               "operator\n[ERROR] forged", "x" * 5000, "hmi:" + "a" * 100, "plc", "\u202eremote")  # fmt: skip


def long_text(rng: random.Random) -> str:
    return rng.choice(
        [
            "y" * rng.choice([257, 4096, 100_000]),
            "bad\nline",
            "esc\x1b[31m",
            "bidi\u202eevil",
            "tab\tx",
        ]
    )


def mutating(rng: random.Random) -> tuple[Any, str, dict[str, Any]]:
    """A request of every service that changes the unit, valid but for its source."""
    return rng.choice(
        [
            (Command, "command", {"command": rng.randint(1, 10)}),
            (SetMode, "set_mode", {"mode": rng.choice([1, 2, 3])}),
            (SetAlarm, "set_alarm", {"id": 1, "value": 0, "active": True, "category": -1}),
            (AckAlarms, "ack_alarms", {"all": True}),
            (ResetAlarms, "reset_alarms", {}),
            (ResetTimes, "reset_times", {"scope": 1}),
            (ResetCounters, "reset_counters", {}),
            (SetMachSpeed, "set_mach_speed", {"mach_speed": 10.0}),
            (SetUnitParameters, "set_unit_parameters",
             {"parameter": [Descriptor(id=1, name="fill", unit="ml", value=1.0)]}),
            (SetProduct, "set_product", {"product": [Product(product_id=7)]}),
            (SetEmActive, "set_em_active", {"em": "nozzle", "active": False}),
            (SetInterlock, "set_interlock", {"active": True, "reason": "blocked"}),
            (SetRemoteCommands, "set_remote_commands", {"enabled": True}),
        ]
    )  # fmt: skip


def hostile(rng: random.Random) -> Iterator[tuple[Any, str, dict[str, Any], set[int]]]:
    """(service type, name, fields, the reason codes a refusal may have), forever."""
    bad = {R.INVALID_ARGUMENT}
    while True:
        kind = rng.randrange(6)
        if kind == 0:  # a remote source while the lock holds (the lock itself: UNAUTHORIZED)
            srv, name, fields = mutating(rng)
            expected = {R.UNAUTHORIZED} if srv is SetRemoteCommands else {R.REMOTE_DISABLED}
            yield srv, name, {**fields, "source": rng.choice(REMOTE)}, expected
        elif kind == 1:  # a source outside the grammar
            srv, name, fields = mutating(rng)
            yield srv, name, {**fields, "source": rng.choice(BAD_SOURCES)}, bad
        elif kind == 2:  # a string past its bound or with a control character
            text = long_text(rng)
            pv = [Descriptor(name=text)]
            yield rng.choice(
                [
                    (SetInterlock, "set_interlock", {"active": True, "reason": text}, bad),
                    (SetAlarm, "set_alarm", {"id": 1, "active": True, "message": text}, bad),
                    (SetEmActive, "set_em_active", {"em": text, "active": False}, bad),
                    (SetMode, "set_mode", {"mode_name": text}, bad),
                    (SetProduct, "set_product", {"product": [Product(process_variables=pv)]}, bad),
                    (SetUnitParameters, "set_unit_parameters", {"parameter": pv}, bad),
                ]
            )
        elif kind == 3:  # arrays past their bound
            many = rng.randint(65, 300)
            products = [Product(product_id=i) for i in range(many)]
            parameters = [Descriptor(id=i, value=1.0) for i in range(many)]
            yield rng.choice(
                [
                    (SetProduct, "set_product", {"product": products}, bad),
                    (SetUnitParameters, "set_unit_parameters", {"parameter": parameters}, bad),
                ]
            )
        elif kind == 4:  # numbers out of range, from a local source
            srv, name, fields, expected = rng.choice(
                [
                    (Command, "command", {"command": rng.choice([0, -1, 11, 2**31 - 1, -(2**31)])},
                     {R.UNKNOWN_COMMAND}),
                    (SetMode, "set_mode", {"mode": rng.choice([0, -3, 32, 4, 2**31 - 1])},
                     {R.MODE_UNKNOWN}),
                    (SetMachSpeed, "set_mach_speed",
                     {"mach_speed": rng.choice([999.0, -1.0, math.nan, math.inf, -math.inf, 1e308])},
                     bad),
                    (SetAlarm, "set_alarm",
                     {"id": 1, "active": True, "category": rng.choice([-2, -1000, 10, 2**31 - 1])},
                     bad),
                    (SetEmActive, "set_em_active", {"em": "ghost", "active": False}, {R.EM_UNKNOWN}),
                    (AckAlarms, "ack_alarms", {"id": rng.randint(2, 10**6)},
                     {R.ALARM_UNKNOWN, R.NOTHING_TO_DO}),
                    (SetInterlock, "set_interlock", {"active": False}, {R.NOTHING_TO_DO}),
                ]
            )  # fmt: skip
            yield srv, name, {**fields, "source": rng.choice(LOCAL)}, expected
        else:  # the remote lock switched from a face
            fields = {"enabled": rng.random() < 0.5, "source": rng.choice(REMOTE)}
            yield SetRemoteCommands, "set_remote_commands", fields, {R.UNAUTHORIZED}


def answers(futures: list[Any], timeout: float) -> int:
    """Wait for every future; how many were left unanswered after ``timeout``."""
    done = threading.Event()
    left = [len(futures)]
    lock = threading.Lock()

    def one(_: Any) -> None:
        with lock:
            left[0] -= 1
            if not left[0]:
                done.set()

    for future in futures:
        future.add_done_callback(one)
    done.wait(timeout)
    return left[0]


def pipelined(ros: Any, clients: dict[tuple[Any, str], Any], base: str,
              batch: list[tuple[Any, str, dict[str, Any], set[int]]]) -> list[tuple[Any, str, set[int]]]:  # fmt: skip
    """Send ``batch`` (service type, name under ``base``, request fields, expected results) at
    once, one client per service kept in ``clients``; every answer, with a description of its
    request and the results expected of it."""
    futures = []
    for srv, name, fields, expected in batch:
        client = clients.get((srv, name))
        if client is None:
            client = ros.node.create_client(srv, f"{base}/{name}", qos_profile=qos.SERVICES)
            assert client.wait_for_service(timeout_sec=10), name
            clients[(srv, name)] = client
        what = f"{name}({ {k: str(v)[:60] for k, v in fields.items()} })"
        futures.append((client.call_async(srv.Request(**fields)), what, expected))
    unanswered = answers([f for f, *_ in futures], 30)
    assert not unanswered, f"{unanswered} of {len(futures)} pipelined requests never answered"
    return [(future.result(), what, expected) for future, what, expected in futures]


def all_refused(answered: list[tuple[Any, str, Any]], counts: dict[int, int]) -> None:
    """Each (response, what, the results it may have) is a refusal with one of them and a
    printable sentence; ``counts`` counts the results."""
    for resp, what, expected in answered:
        text = resp.message_out if hasattr(resp, "message_out") else resp.message
        assert not resp.accepted, f"{what} accepted: {text}"
        assert resp.result in expected, f"{what}: result {resp.result}: {text}"
        assert 10 < len(text) < 600 and text.isprintable(), f"{what}: {text[:300]!r}"
        counts[resp.result] = counts.get(resp.result, 0) + 1


def rss_mb(pid: int | None = None) -> float:
    """The resident memory of process ``pid`` (this one by default), MB."""
    with open(f"/proc/{pid or os.getpid()}/status") as f:
        return int(next(line for line in f if line.startswith("VmRSS")).split()[1]) / 1024


def test_thousands_of_hostile_service_requests_and_reports_change_nothing(
    ros: Any, make_unit: Any, capfd: pytest.CaptureFixture[str]
) -> None:
    unit = make_unit(UNIT_DOC)
    em = FakeEm(ros, unit, "nozzle", lease=2.0, period=0.2)
    em.start_heartbeats()
    unit.client.wait_status(lambda m: all(e.online for e in m.equipment_modules), what="EM online")
    before = unit.client.status.last
    # what the unit published, counted by the unit itself: the status, the transition and the
    # alarm list of one input may arrive in any order under load (a collector's count races them)
    published = dict(unit.node._published)
    inputs = ros.subscribe(UnitInput, f"{unit.base}/input_log", qos.INPUT_LOG)
    first_input = unit.node._input_index
    capfd.readouterr()

    clients: dict[tuple[Any, str], Any] = {}
    rng = random.Random(SEED)
    requests = hostile(rng)
    counts: dict[int, int] = {}
    rss_before = 0.0
    started = time.monotonic()
    sent = 0
    while sent < COUNT:
        if sent >= WARM_UP and not rss_before:
            rss_before = rss_mb()
        batch = [next(requests) for _ in range(BATCH)]
        all_refused(pipelined(ros, clients, unit.base, batch), counts)
        sent += len(batch)
    rss_after = rss_mb()

    # forged EM reports: made-up EMs, fields out of range, and the configured EM from another writer
    forger = rclpy.create_node("forger", namespace=f"/{unit.cell}/filler", context=ros.context)
    pub = forger.create_publisher(EmReport, "em_reports", qos.EM_REPORTS)
    ros.add(forger)
    wait_until(lambda: pub.get_subscription_count() >= 1, what="the unit subscribed")
    refused = unit.node.refused_reports
    for i in range(REPORTS):
        kind = i % 4
        if kind == 0:
            msg = EmReport(em=f"fake{i}", kind=EmReport.KIND_HEARTBEAT)
        elif kind == 1:
            msg = EmReport(em="nozzle", kind=EmReport.KIND_STATE_COMPLETE,
                           state=before.state_current, sequence=before.sequence)  # fmt: skip
        elif kind == 2:
            msg = EmReport(
                em=rng.choice(["x" * 300, "a\nb", "nozzle"]), kind=rng.choice([7, 99, 255])
            )
        else:
            msg = EmReport(em="nozzle", kind=EmReport.KIND_ALARM, alarm_id=1, alarm_active=True,
                           category=0, warning=True, message="relabelled")  # fmt: skip
        pub.publish(msg)
        if i % 100 == 99:  # the topic keeps 200: let the unit catch up (3 in 4 are refused
            # here, the made-up EMs by the engine; the reports of one writer arrive in order)
            seen = refused + (i + 1) * 3 // 4
            wait_until(lambda n=seen: unit.node.refused_reports >= n, 10, "reports")
    wait_until(lambda: unit.node.refused_reports >= refused + REPORTS * 3 // 4, 10, "reports")
    elapsed = time.monotonic() - started

    last_input = unit.node._input_index
    inputs.wait_for(lambda m: m.index >= last_input, 10, "the input log flushed")
    log = capfd.readouterr()
    em.stop_heartbeats()
    after = unit.client.status.last
    changed = {
        t: unit.node._published[t] - published[t] for t in ("status", "transitions", "alarms")
    }
    changed = {t: n for t, n in changed.items() if n}
    assert not changed, f"a refused request or report published {changed}"
    assert (after.state_current, after.unit_mode_current, after.mach_speed) == (
        before.state_current, before.unit_mode_current, before.mach_speed)  # fmt: skip
    assert [e.name for e in after.equipment_modules] == ["nozzle"]
    assert not after.remote_commands_enabled
    growth = rss_after - rss_before
    assert growth < MAX_RSS_GROWTH_MB, f"RSS grew {growth:.1f} MB"
    size = len(log.out) + len(log.err)
    assert size < MAX_LOG_BYTES, f"{size} bytes of log"
    assert "[ERROR] forged" not in log.err.replace("\\n[ERROR] forged", "")
    assert sum(counts.values()) >= COUNT and {R.REMOTE_DISABLED, R.INVALID_ARGUMENT} <= set(counts)
    # item 4: what the boundary refused never reached the engine's input log; no record is large
    recorded = [m for m in inputs.messages if first_input < m.index <= last_input]
    reached_engine = sum(n for r, n in counts.items() if r != R.INVALID_ARGUMENT) + REPORTS // 4
    print(
        f"input log: {last_input - first_input} records, {reached_engine} requests reached the engine"
    )
    assert last_input - first_input <= reached_engine, (last_input - first_input, reached_engine)
    assert max(len(m.args_json) for m in recorded) < 4 * MAX_REQUEST_TEXT
    print(f"{sent} requests + {REPORTS} reports in {elapsed:.1f} s; RSS {growth:+.1f} MB; "
          f"log {size} bytes; {counts}")  # fmt: skip


def test_a_forged_state_complete_never_ends_resetting_the_ems_own_does(
    ros: Any, make_unit: Any
) -> None:
    """Issue 15 item 3: a second writer's State Complete for a configured EM (right state and
    sequence) used to end Resetting early; only the writer that speaks for the EM is heard."""
    unit = make_unit({"equipment_modules": {"nozzle": {}}})
    em = FakeEm(ros, unit, "nozzle", lease=2.0, period=0.2)
    em.start_heartbeats()
    unit.client.wait_status(lambda m: all(e.online for e in m.equipment_modules), what="EM online")
    forger = rclpy.create_node("forger", namespace=f"/{unit.cell}/filler", context=ros.context)
    pub = forger.create_publisher(EmReport, "em_reports", qos.EM_REPORTS)
    ros.add(forger)
    wait_until(lambda: pub.get_subscription_count() >= 1, what="the unit subscribed")
    assert unit.command(1).accepted
    resetting = unit.wait_state("RESETTING")
    refused = unit.node.refused_reports
    for _ in range(5):
        pub.publish(EmReport(em="nozzle", kind=EmReport.KIND_STATE_COMPLETE,
                             state=resetting.state_current, sequence=resetting.sequence))  # fmt: skip
    wait_until(lambda: unit.node.refused_reports >= refused + 5, 10, "the forged reports refused")
    now = unit.client.status.last
    assert (now.state_current, now.sequence) == (resetting.state_current, resetting.sequence)
    assert not next(e for e in now.equipment_modules if e.name == "nozzle").state_complete
    em.complete(resetting)
    unit.wait_state("IDLE")
    em.stop_heartbeats()


COORDINATOR_REQUESTS = 1000


def test_hostile_cell_requests_at_the_coordinator_change_nothing(ros: Any, tmp_path: Any) -> None:
    """The coordinator's services under the same attack (commands, modes, Trigger shortcuts):
    sources outside the grammar, long or controlling text, numbers out of range, and valid cell
    commands while the units' remote lock holds: each answered, refused with a reason, and no
    unit changes."""
    from std_srvs.srv import Trigger

    from test.ros.test_coordinator import Cell

    cell = Cell(ros, tmp_path, {"filler": {}, "capper": {}}, {"start_order": ["filler", "capper"]})
    before = {n: c.status.last for n, c in cell.units.items()}
    for c in cell.units.values():  # the latched RESTART transition may arrive after the status
        c.transitions.wait_for(
            lambda t: t.trigger == TransitionEvent.TRIGGER_RESTART, 10, "RESTART"
        )
    marks = {n: (len(c.status), len(c.transitions)) for n, c in cell.units.items()}
    base = f"/{cell.name}/coordinator"
    rng = random.Random(SEED)
    locked = {R.REMOTE_DISABLED, R.COMMAND_NOT_ALLOWED}  # (or busy with another request)
    modes = {R.REMOTE_DISABLED, R.COMMAND_NOT_ALLOWED, R.MODE_UNKNOWN, R.MODE_CHANGE_NOT_ALLOWED}
    requests: list[tuple[Any, str, dict[str, Any], set[int]]] = []
    for _ in range(COORDINATOR_REQUESTS):
        # not STOP, ABORT (never refused) or CLEAR (the units are Stopped already: nothing to do)
        cmd = rng.choice([1, 2, 4, 5, 6, 7, 10])
        requests.append(rng.choice([
            (Command, "command", {"command": cmd, "source": rng.choice(REMOTE + LOCAL)}, locked),
            (Command, "command", {"command": rng.choice([0, 11, -7, 2**31 - 1])}, {R.UNKNOWN_COMMAND}),
            (Command, "command", {"command": cmd, "source": rng.choice(BAD_SOURCES)}, {R.INVALID_ARGUMENT}),
            (SetMode, "set_mode", {"mode": rng.choice([0, 2, 3, 99, -1])}, modes),
            (SetMode, "set_mode", {"mode_name": long_text(rng)}, {R.INVALID_ARGUMENT}),
            (Trigger, rng.choice(["reset", "start", "hold", "unsuspend"]), {}, locked),
        ]))  # fmt: skip
    clients: dict[tuple[Any, str], Any] = {}
    counts: dict[int, int] = {}
    for start in range(0, len(requests), 50):
        for resp, what, expected in pipelined(ros, clients, base, requests[start : start + 50]):
            if isinstance(resp, Trigger.Response):
                assert not resp.success and 10 < len(resp.message) < 2000, f"{what}: {resp.message}"
                continue
            assert not resp.accepted and resp.result in expected, (
                f"{what}: {resp.result} {resp.message}"
            )
            assert 10 < len(resp.message) < 2000 and resp.message.isprintable(), (
                f"{what}: {resp.message!r}"
            )
            counts[resp.result] = counts.get(resp.result, 0) + 1
    for name, client in cell.units.items():
        assert (len(client.status), len(client.transitions)) == marks[name], name
        now = client.status.last
        assert (now.state_current, now.unit_mode_current) == (
            before[name].state_current, before[name].unit_mode_current)  # fmt: skip
    assert {R.REMOTE_DISABLED, R.INVALID_ARGUMENT, R.UNKNOWN_COMMAND} <= set(counts)


LINE_REQUESTS = 1200
DAYS = ("9999-12-31", "0001-01-01", "2262-04-12", "2038-01-19", "1970-01-01", "2025-06-16",
        "2025-02-30", "+2025-01-01", "20250616")  # fmt: skip
WINDOWS = ("", "shift", "shift:current", "shift:previous", "15min", "1h", "reset", "lifetime",
           "since", "shifts", "trend", "shift:", "nonsense", *(f"shift:{d} {s}" for d in DAYS
           for s in ("early", "night", "x")))  # fmt: skip
SECONDS = (0, 1, 2**31 - 1, -(2**31), 1_750_000_000)  # Time.sec is int32
NANOS = (0, 999_999_999, 2**32 - 1)  # Time.nanosec is uint32
STEPS = (0.0, -1.0, 1e-300, 900.0, 1e7, 1e300, math.inf, -math.inf, math.nan)
COUNTS = (0, 1, 200, 201, 2**31 - 1, 2**32 - 1)  # uint32


def line_requests(rng: random.Random) -> Iterator[tuple[Any, str, dict[str, Any], set[int]]]:
    """Every field of ``line/query_losses`` and ``line/query_episodes`` at and past its extremes."""
    from builtin_interfaces.msg import Time
    from packml_interfaces.srv import QueryEpisodes, QueryLosses

    def stamp() -> Time:
        return Time(sec=rng.choice(SECONDS), nanosec=rng.choice(NANOS))

    any_answer = {R.ACCEPTED, R.INVALID_ARGUMENT}
    while True:
        if rng.random() < 0.7:
            yield QueryLosses, "line/query_losses", {
                "window": rng.choice(WINDOWS), "since": stamp(), "until": stamp(),
                "step": rng.choice(STEPS), "count": rng.choice(COUNTS)}, any_answer  # fmt: skip
        else:
            yield QueryEpisodes, "line/query_episodes", {
                "since": stamp(), "until": stamp(), "unit": rng.choice(["", "cell", "filler", "ghost"]),
                "bucket": rng.choice(["", "starved", "x"]), "reason": rng.choice(["", "jam"]),
                "open_only": rng.random() < 0.5, "limit": rng.choice(COUNTS)}, any_answer  # fmt: skip


def test_no_line_query_ends_the_coordinator(ros: Any, tmp_path: Any, processes: Any) -> None:
    """Issue 25 item 1: ``line/query_losses`` with window ``shift:9999-12-31 early`` raised an
    OverflowError in the shift calendar, which escaped the callback: the coordinator process
    exited. A seeded fuzz of every field of the line queries against a coordinator process with
    a shift calendar: each request is answered (a refusal says why), the process lives on, and
    its log holds no traceback."""
    import yaml
    from packml_interfaces.srv import QueryLosses

    from test.ros.cells import write_cell

    path, cell = write_cell(tmp_path, {"filler": {}, "packer": {}})
    doc = yaml.safe_load(path.read_text())
    doc["line"] = {"order": ["filler", "packer"], "timezone": "Europe/Berlin", "shifts": {
        "early": {"start": "06:00", "end": "14:00"}, "night": {"start": "22:00", "end": "06:00"}}}  # fmt: skip
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    coordinator = processes.module("coordinator", "packml_ros2.coordinator_node", str(path))
    base = f"/{cell}/coordinator"
    ros.wait_for_service(QueryLosses, f"{base}/line/query_losses", 30)
    clients: dict[tuple[Any, str], Any] = {}
    first = pipelined(ros, clients, base, [(QueryLosses, "line/query_losses",
                                           {"window": "shift:9999-12-31 early"}, set())])  # fmt: skip
    resp = first[0][0]
    assert (resp.accepted, resp.result) == (False, R.INVALID_ARGUMENT), resp.message
    assert "9999-12-31 early" in resp.message, resp.message
    rng = random.Random(SEED)
    requests = line_requests(rng)
    counts: dict[int, int] = {}
    for _ in range(LINE_REQUESTS // 100):
        for resp, what, expected in pipelined(ros, clients, base, [next(requests) for _ in range(100)]):  # fmt: skip
            assert resp.result in expected, f"{what}: {resp.result} {resp.message}"
            assert resp.accepted == (resp.result == R.ACCEPTED), what
            assert 0 < len(resp.message) < 600 and resp.message.isprintable(), what
            assert "could not handle" not in resp.message, f"{what}: {resp.message}"
            counts[resp.result] = counts.get(resp.result, 0) + 1
        assert coordinator.running(), coordinator.output()[-3000:]
    assert set(counts) == {R.ACCEPTED, R.INVALID_ARGUMENT}, counts
    assert "Traceback" not in coordinator.output(), coordinator.output()[-3000:]


FAULTY_NODE = """
import sys
from packml_interfaces.srv import Command
from std_msgs.msg import String
from std_srvs.srv import Trigger
from packml_ros2 import responses, run
from packml_ros2.boundary import GuardedNode

run.init()
node = GuardedNode("faulty", namespace=sys.argv[1])
def boom(*args):
    raise OverflowError("date value out of range (opc.tcp://plc:s3cret-pw@10.0.0.1:4840)")
responses.create_service(node, Command, "~/command", boom)
node.create_service(Trigger, "~/trigger", boom)
node.create_subscription(String, "~/in", boom, 10)
node.create_timer(0.02, boom)
node.declare_parameter("x", 1)
node.add_on_set_parameters_callback(boom)
print("up", flush=True)
sys.exit(run.spin([node]))
"""


def test_no_callback_that_raises_ends_a_node(ros: Any, processes: Any) -> None:
    """Issue 25 item 1: the boundary of every callback. A node process (the EventsExecutor, as
    every node runs) whose service handlers, topic callback, timer and parameter check all raise:
    each request is answered as a refusal naming the exception's type, the node lives on, and its
    log has one bounded, rate-limited line per kind of failure, no traceback, no URL password."""
    from rcl_interfaces.msg import Parameter, ParameterValue
    from rcl_interfaces.srv import SetParameters
    from std_msgs.msg import String
    from std_srvs.srv import Trigger

    ns = f"/faulty{os.getpid()}"
    proc = processes.start("faulty", "-c", FAULTY_NODE, ns)
    base = f"{ns}/faulty"
    pub = ros.node.create_publisher(String, f"{base}/in", 10)
    for i in range(30):
        answer = ros.call(Command, f"{base}/command", Command.Request(command=1), 30)
        assert (answer.accepted, answer.result) == (False, R.INVALID_ARGUMENT), answer
        assert answer.message == f"refused: {base}/command could not handle this request (OverflowError); see its log"  # fmt: skip
        trigger = ros.call(Trigger, f"{base}/trigger", Trigger.Request(), 10)
        assert not trigger.success and "(OverflowError)" in trigger.message, trigger
        pub.publish(String(data=str(i)))
    value = ParameterValue(type=2, integer_value=5)
    params = ros.call(SetParameters, f"{base}/set_parameters",
                      SetParameters.Request(parameters=[Parameter(name="x", value=value)]), 10)  # fmt: skip
    assert not params.results[0].successful and "OverflowError" in params.results[0].reason
    wait_until(lambda: pub.get_subscription_count() >= 1, what="the node subscribed")
    pub.publish(String(data="last"))
    wait_until(lambda: "topic" in proc.output(), 10, "the topic callback's failure logged")
    assert proc.running(), proc.output()[-3000:]
    log = proc.output()
    assert "Traceback" not in log and "s3cret" not in log, log[-3000:]
    failures = [line for line in log.splitlines() if "failed: OverflowError" in line]
    kinds = {k for k in ("/command", "/trigger", "topic", "a timer", "parameter check") if any(k in f for f in failures)}  # fmt: skip
    assert kinds == {"/command", "/trigger", "topic", "a timer", "parameter check"}, log[-3000:]
    assert len(failures) <= 5 * 5 and all(len(f) < 800 for f in failures), len(failures)
    assert "(at " in failures[0] and "<redacted>@10.0.0.1" in failures[0], failures[0]
