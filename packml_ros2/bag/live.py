"""``packml replay <bag> --live [--speed X]``: feed a recording to running unit nodes.

Start the unit nodes of the recording first (fresh: in STOPPED; without their EMs, whose reports
come from the bag), e.g. ``python -m packml_ros2.unit_node <cell.yaml> <unit>`` with the cell file
of the recording. Then, at the recorded pace divided by ``--speed``:

- every recorded EM report is published on ``<unit>/em_reports`` (heartbeats too, so the unit
  sees the EMs alive; State Complete sequence numbers are shifted by the difference between the
  live unit's and the recorded unit's start-up sequence number; when the input log shows the
  unit saw an EM before the recorder caught its first report, a heartbeat stands in for it);
- every recorded operator/remote input is sent through the unit's services with its recorded
  source: ``command``, ``set_mode``, ``ack_alarms``, ``reset_alarms``, ``reset_times``,
  ``reset_counters``, ``set_alarm``, ``set_mach_speed``, ``set_unit_parameters``, ``set_product``,
  ``set_em_active``, ``set_interlock``, and the ``remote_commands_enabled`` parameter. Inputs the
  unit derived from EM reports (``em_*``, and commands/alarms with an ``em:`` source) are not sent
  twice; ``step`` inputs (engine API only) cannot be replayed live.

What ``--live`` compares — loosely, because live timing is real: the sequence of transitions
(from-state, to-state, from-mode, to-mode, trigger; not times, sequence numbers, sources or
details) after the start-up transition, and the final state and mode. Status, admin data and
alarm lists are not compared (times differ by nature). When the recording began after the unit
started, the recorded transitions must equal the last ones of the live run. Time-dependent
behaviour (EM leases, state timeouts, dwell times) happens in real time on the live unit, so
``--speed`` above 1 can change the outcome of recordings that depend on it (an EM lost).
"""

from __future__ import annotations

import json
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rclpy.serialization import deserialize_message, serialize_message

from .. import convert
from ..client import Unavailable, call_blocking
from ..core import inputlog
from ..core.numbers import state_name
from ..ros import interface
from .recording import Input, UnitRecording, load
from .replay import checked_inputs, stamp_of
from .topics import UNIT_TOPICS, msg_class

EM_INPUTS = inputlog.EM_INPUTS
NOT_LIVE = frozenset({inputlog.START, inputlog.ADVANCE.name, inputlog.STEP.name})


@dataclass
class Action:
    time: float
    order: int
    kind: str  # "report" | "service" | "parameter"
    what: str
    payload: Any = None


@dataclass
class LiveUnitResult:
    unit: str
    recorded: list[tuple[Any, ...]]  # (from, to, from mode, to mode, trigger, source)
    live: list[tuple[Any, ...]]
    from_start: bool  # the recording holds the unit's start-up transition
    final_recorded: tuple[str, int] | None
    final_live: tuple[str, int] | None
    refused: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)

    def compared_live(self) -> list[tuple[Any, ...]]:
        """The live transitions the recorded ones are compared with (all, or the last ones)."""
        if self.from_start or len(self.live) < len(self.recorded):
            return self.live
        return self.live[len(self.live) - len(self.recorded) :]

    def first_difference(self) -> int | None:
        live = self.compared_live()
        for i, (a, b) in enumerate(zip(self.recorded, live, strict=False)):
            if a[:5] != b[:5]:
                return i
        if len(self.recorded) != len(live):
            return min(len(self.recorded), len(live))
        return None

    @property
    def ok(self) -> bool:
        return self.first_difference() is None and self.final_recorded == self.final_live


@dataclass
class LiveResult:
    path: Path
    speed: float
    units: list[LiveUnitResult]
    seconds: float

    @property
    def ok(self) -> bool:
        return all(u.ok for u in self.units)

    def report(self) -> str:
        verdict = "match" if self.ok else "MISMATCH"
        parts = [
            f"{u.unit}: {len(u.recorded)} transitions recorded, {len(u.live)} live"
            for u in self.units
        ]
        lines = [
            f"{self.path}: --live at speed {self.speed:g}: {verdict} ({'; '.join(parts)}; {self.seconds:.1f} s)"
        ]
        for u in self.units:
            for s in u.skipped:
                lines.append(f"  {u.unit}: not replayed live: {s}")
            for r in u.refused:
                lines.append(f"  {u.unit}: refused by the live unit: {r}")
            i = u.first_difference()
            if i is not None:
                lines.append(f"  {u.unit}: first different transition #{i + 1}:")
                lines.append(f"    recorded: {_text(u.recorded, i)}")
                lines.append(f"    live:     {_text(u.compared_live(), i)}")
            if u.final_recorded != u.final_live:
                lines.append(
                    f"  {u.unit}: final state/mode recorded {u.final_recorded}, live {u.final_live}"
                )
        return "\n".join(lines)


def _text(items: list[tuple[Any, ...]], i: int) -> str:
    if i >= len(items):
        return "(none)"
    f, t, fm, tm, trig, src = items[i][:6]
    modes = f", mode {fm} -> {tm}" if fm != tm else ""
    return f"{f} -> {t}{modes} [{trig}] from {src}"


def _key(m: Any) -> tuple[Any, ...]:
    return (m.from_state_name, m.to_state_name, m.from_mode, m.to_mode, m.trigger_name, m.source)


def service_request(i: Input) -> tuple[str, dict[str, Any]] | None:
    """The unit service (and request fields) that makes the unit log input ``i``; None when it
    came from an EM report (or cannot be sent live)."""
    a = i.args
    source = a.get("source", "operator")
    if i.name in EM_INPUTS or i.name in NOT_LIVE or str(source).startswith("em:"):
        return None
    if i.name == inputlog.COMMAND.name:
        return "command", {"command": int(a["command"]), "source": source}
    if i.name == inputlog.MODE.name:
        mode = a["mode"]
        if isinstance(mode, str) and not mode.strip().isdigit():
            return "set_mode", {"mode_name": mode, "source": source}
        return "set_mode", {"mode": int(mode), "source": source}
    if i.name == inputlog.ALARM_ACK.name:
        every = a.get("id") is None
        return "ack_alarms", {
            "all": every,
            "id": 0 if every else int(a["id"]),
            "value": int(a.get("value", 0)),
            "source": source,
        }
    if i.name == inputlog.ALARM_RESET.name:
        return "reset_alarms", {"clear_first_out": bool(a.get("clear_first_out")), "source": source}
    if i.name == inputlog.TIMES_RESET.name:
        return "reset_times", {"scope": 1 if a.get("all") else 0, "source": source}
    if i.name == inputlog.COUNTERS_RESET.name:
        return "reset_counters", {"source": source}
    if i.name == inputlog.ALARM.name:
        return "set_alarm", {
            "id": int(a["id"]),
            "value": int(a.get("value", 0)),
            "active": bool(a.get("active", True)),
            "warning": bool(a.get("warning")),
            "category": int(a.get("category", -1)),
            "message": a.get("message", ""),
            "source": source,
        }
    if i.name == inputlog.SPEED.name:
        return "set_mach_speed", {"mach_speed": float(a["speed"]), "source": source}
    if i.name == inputlog.PARAMETERS.name:
        desc = msg_class("packml_interfaces/msg/Descriptor")
        params = [
            desc(id=int(d["id"]), name=d["name"], unit=d["unit"], value=float(d["value"]))
            for d in a["parameters"]
        ]
        return "set_unit_parameters", {"parameter": params, "source": source}
    if i.name == inputlog.PRODUCTS.name:
        products = [convert.product(inputlog.product_from_dict(p)) for p in a["products"]]
        return "set_product", {"product": products, "source": source}
    if i.name == inputlog.EM_ACTIVE.name:
        return "set_em_active", {"em": a["em"], "active": bool(a["active"]), "source": source}
    if i.name == inputlog.INTERLOCK.name:
        return "set_interlock", {
            "active": bool(a["active"]),
            "reason": a.get("reason", ""),
            "source": source,
        }
    return None


class _LiveUnit:
    """One running unit: its services, em_reports publisher and transitions/status seen."""

    def __init__(self, node: Any, rec: UnitRecording) -> None:
        from ..client import SERVICES

        self.node = node
        self.rec = rec
        self.prefix = rec.prefix
        self.cond = threading.Condition()
        self.transitions: list[Any] = []
        self.status: Any = None
        for name, callback in (("transitions", self._on_transition), ("status", self._on_status)):
            t = interface.TOPIC[name]
            node.create_subscription(t.type, t.path(self.prefix), callback, t.qos)
        reports = interface.TOPIC["em_reports"]
        self.reports = node.create_publisher(reports.type, reports.path(self.prefix), reports.qos)
        self.services = SERVICES
        self.clients: dict[str, Any] = {}

    def _on_transition(self, msg: Any) -> None:
        with self.cond:
            self.transitions.append(msg)
            self.cond.notify_all()

    def _on_status(self, msg: Any) -> None:
        with self.cond:
            self.status = msg
            self.cond.notify_all()

    def wait(self, predicate: Callable[[], bool], timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        with self.cond:
            while not predicate():
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self.cond.wait(min(left, 0.05))
            return True

    def client(self, name: str) -> Any:
        if name not in self.clients:
            if name == "parameters":
                from rcl_interfaces.srv import SetParameters

                self.clients[name] = self.node.create_client(
                    SetParameters, f"{self.prefix}/set_parameters"
                )
            else:
                self.clients[name] = self.node.create_client(
                    self.services[name], f"{self.prefix}/{name}"
                )
        return self.clients[name]

    def call(self, name: str, request: Any, timeout: float) -> Any:
        return call_blocking(self.client(name), request, timeout, f"{self.prefix}/{name}")


def _actions(
    rec: UnitRecording, inputs: list[Input], offset: int, skipped: list[str]
) -> list[Action]:
    report_cls = msg_class(UNIT_TOPICS["em_reports"])
    actions: list[Action] = []
    order = 0
    for _, recorded in rec.em_reports:
        msg = deserialize_message(recorded, report_cls)
        data = recorded
        if msg.kind == report_cls.KIND_STATE_COMPLETE and offset:
            msg.sequence = max(0, msg.sequence + offset)
            data = serialize_message(msg)
        actions.append(Action(stamp_of(msg), order, "report", msg.em, data))
        order += 1
    # The unit saw an EM (em_seen) whose first reports the recorder missed (em_reports is not
    # latched: a recorder matches a freshly started EM only after its first heartbeats): a
    # heartbeat at that moment stands in for them.
    first_report: dict[str, float] = {}
    leases: dict[str, float] = {}
    for a in actions:
        first_report.setdefault(a.what, a.time)
    for _, recorded in rec.em_reports:
        m = deserialize_message(recorded, report_cls)
        leases.setdefault(m.em, m.lease)
    for i in inputs[1:]:
        name = i.args.get("em", "")
        if i.name == inputlog.EM_SEEN.name and first_report.get(name, math.inf) > i.time:
            beat = report_cls(
                stamp=convert.stamp(i.time),
                em=name,
                kind=report_cls.KIND_HEARTBEAT,
                lease=leases.get(name, 0.0),
            )
            actions.append(Action(i.time, order, "report", name, serialize_message(beat)))
            order += 1
            first_report[name] = i.time
    for i in inputs[1:]:
        if i.name == inputlog.REMOTE.name:
            actions.append(Action(i.time, order, "parameter", i.name, bool(i.args["enabled"])))
        elif i.name == inputlog.STEP.name:
            skipped.append(f"input #{i.index} step {i.args_json}")
            continue
        else:
            req = service_request(i)
            if req is None:
                continue
            actions.append(Action(i.time, order, "service", req[0], req[1]))
        order += 1
    actions.sort(key=lambda a: (a.time, a.order))
    return actions


def replay_live(
    path: str | Path,
    speed: float = 1.0,
    units: Sequence[str] = (),
    timeout: float = 10.0,
    settle: float = 5.0,
    domain_id: int | None = None,
) -> LiveResult:
    """Feed the recording at ``path`` to the running units (see the module docstring)."""
    import rclpy
    from rclpy.context import Context

    from .. import run
    from ..boundary import GuardedNode as Node
    from ..executors import MultiThreadedExecutor, spin_in_thread

    if speed <= 0:
        raise ValueError("--speed must be > 0")
    t_start = time.monotonic()
    rec = load(path)
    chosen = [rec.unit(u) for u in units] if units else list(rec.units.values())
    run.default_environment(tool=True)
    context = Context()
    kwargs: dict[str, Any] = {
        "context": context,
        "signal_handler_options": rclpy.signals.SignalHandlerOptions.NO,
    }
    if domain_id is not None:
        kwargs["domain_id"] = domain_id
    rclpy.init(**kwargs)
    node = Node(f"packml_replay_live_{threading.get_ident() % 100000}", context=context)
    executor = MultiThreadedExecutor(context=context)
    thread = spin_in_thread(executor, node)
    try:
        return _run(rec.path, node, chosen, speed, timeout, settle, t_start)
    finally:
        executor.shutdown(timeout_sec=2)
        node.destroy_node()
        rclpy.try_shutdown(context=context)
        thread.join(2)


def _run(
    path: Path,
    node: Any,
    chosen: list[UnitRecording],
    speed: float,
    timeout: float,
    settle: float,
    t_start: float,
) -> LiveResult:
    tcls = msg_class(UNIT_TOPICS["transitions"])
    scls = msg_class(UNIT_TOPICS["status"])
    lives: list[_LiveUnit] = []
    plans: list[
        tuple[
            _LiveUnit, list[Action], list[tuple[Any, ...]], bool, tuple[str, int] | None, list[str]
        ]
    ] = []
    for rec in chosen:
        inputs = checked_inputs(rec, path)
        live = _LiveUnit(node, rec)
        lives.append(live)
        if not live.wait(lambda lv=live: lv.status is not None, timeout):  # type: ignore[misc]
            raise Unavailable(f"unit {rec.prefix} is not running (no status within {timeout:g} s)")
        if live.status.state_current_name != "STOPPED":
            raise Unavailable(
                f"the live unit {rec.prefix} is {live.status.state_current_name}: --live needs "
                "freshly started units (STOPPED), without their EMs"
            )
        recorded_t = [deserialize_message(raw, tcls) for raw in rec.outputs.get("transitions", [])]
        start_doc = inputs[0].args.get("document") or {}
        restart_seq = int(start_doc.get("sequence", 0)) + 1
        offset = live.status.sequence - restart_seq
        skipped: list[str] = []
        actions = _actions(rec, inputs, offset, skipped)
        keys = [_key(m) for m in recorded_t if m.trigger_name != "RESTART"]
        from_start = bool(recorded_t) and recorded_t[0].trigger_name == "RESTART"
        statuses = rec.outputs.get("status", [])
        final = None
        if statuses:
            s = deserialize_message(statuses[-1], scls)
            final = (s.state_current_name, s.unit_mode_current)
        plans.append((live, actions, keys, from_start, final, skipped))
        if not live.wait(lambda lv=live: lv.reports.get_subscription_count() > 0, timeout):  # type: ignore[misc]
            raise Unavailable(f"{rec.prefix}/em_reports has no subscriber (is the unit running?)")
    merged = sorted(
        ((a, lv) for lv, acts, *_ in plans for a in acts), key=lambda x: (x[0].time, x[0].order)
    )
    refused: dict[str, list[str]] = {lv.prefix: [] for lv in lives}
    # Before the clock starts: every service the timeline calls is there; and after the first
    # report to a unit, the clock waits until the unit shows that EM online (its subscription has
    # matched us too: until then DDS may hold reports back for seconds, upsetting the pace).
    for action, live in merged:
        if action.kind != "report":
            name = "parameters" if action.kind == "parameter" else action.what
            if not live.client(name).wait_for_service(timeout_sec=timeout):
                raise Unavailable(f"{live.prefix}/{name} is not available")
    if merged:
        t0 = merged[0][0].time
        first: set[str] = set()
        w0 = time.monotonic()
        for action, live in merged:
            delay = w0 + (action.time - t0) / speed - time.monotonic()
            if delay > 0:
                time.sleep(delay)  # the recorded pace: the purpose of --live, not a wait for DDS
            _do(live, action, timeout, refused[live.prefix])
            if action.kind == "report" and live.prefix not in first:
                first.add(live.prefix)
                began = time.monotonic()
                if not live.wait(lambda lv=live, em=action.what: _online(lv.status, em), timeout):  # type: ignore[misc]
                    raise Unavailable(f"{live.prefix} does not see the reports of EM {action.what}")
                w0 += time.monotonic() - began  # the pace starts over once the unit hears us
    results = []
    for live, _, keys, from_start, final, skipped in plans:
        want = len(keys)

        def enough(lv: _LiveUnit = live, n: int = want) -> bool:
            """As many transitions as recorded, and the status of the last one."""
            seen = [m for m in lv.transitions if m.trigger_name != "RESTART"]
            return len(seen) >= n and (
                not seen or (lv.status is not None and lv.status.sequence >= seen[-1].sequence)
            )

        live.wait(enough, settle)
        with live.cond:
            got = [_key(m) for m in live.transitions if m.trigger_name != "RESTART"]
            status = live.status
        final_live = (status.state_current_name, status.unit_mode_current) if status else None
        results.append(
            LiveUnitResult(
                live.rec.name,
                keys,
                got,
                from_start,
                final,
                final_live,
                refused[live.prefix],
                skipped,
            )
        )
    return LiveResult(path, speed, results, time.monotonic() - t_start)


def _do(live: _LiveUnit, action: Action, timeout: float, refused: list[str]) -> None:
    if action.kind == "report":
        live.reports.publish(action.payload)
        return
    if action.kind == "parameter":
        from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
        from rcl_interfaces.srv import SetParameters

        value = ParameterValue(type=ParameterType.PARAMETER_BOOL, bool_value=action.payload)
        req = SetParameters.Request(
            parameters=[Parameter(name="remote_commands_enabled", value=value)]
        )
        live.call("parameters", req, timeout)
        return
    srv = live.services[action.what]
    resp = live.call(action.what, srv.Request(**action.payload), timeout)
    accepted = getattr(resp, "accepted", True)
    if not accepted:
        text = getattr(resp, "message", "") or getattr(resp, "message_out", "")
        refused.append(f"{action.what} {json.dumps(_plain(action.payload))}: {text}")


def _online(status: Any, em: str) -> bool:
    return status is not None and any(e.name == em and e.online for e in status.equipment_modules)


def _plain(payload: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in payload.items() if isinstance(v, (int, float, str, bool))}


__all__ = ["LiveResult", "Unavailable", "replay_live", "service_request", "state_name"]
