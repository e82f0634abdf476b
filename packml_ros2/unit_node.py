"""The PackML unit node: the engine (:class:`packml_ros2.core.Unit`) on ROS 2.

Its services and topics (relative to the node, e.g. ``/demo_cell/robot_cell/command``) are the
ones :mod:`packml_ros2.ros.interface` declares (``unit_node --help`` lists them after this text);
EMs report on ``em_reports`` and ``em_heartbeats``.

Run: ``unit_node <cell.yaml> [unit] [--ros-args -p remote_commands_enabled:=true ...]``
"""

from __future__ import annotations

import json
import math
import sys
import time
from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path
from typing import Any, TypeVar

from packml_interfaces.msg import EmReport, UnitInput
from packml_interfaces.srv import (
    AckAlarms,
    Command,
    QueryAlarms,
    ResetAlarms,
    ResetCounters,
    ResetTimes,
    SetAlarm,
    SetEmActive,
    SetInterlock,
    SetMachSpeed,
    SetMode,
    SetProduct,
    SetUnitParameters,
)
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.event_handler import PublisherEventCallbacks, QoSPublisherMatchedInfo
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.subscription import MessageInfo
from std_msgs.msg import String
from std_srvs.srv import Trigger

from . import convert, run
from .boundary import GuardedNode
from .core import (
    CellConfig,
    Cmd,
    ConfigError,
    Store,
    StoreError,
    Unit,
    UnitConfig,
    inputlog,
    load_cell,
    state_name,
)
from .core.config import CoordinatorConfig
from .core.durable import TIME_CHECKPOINT
from .core.limits import LogLimiter, printable
from .core.liveliness import Liveliness
from .core.recipes import inline_recipes
from .core.reports import LEAVE, Writers, report_problem
from .core.secrets import redacted_yaml
from .driver import FrozenClock, UnitDriver
from .presence import with_info
from .remote_lock import RemoteLock
from .ros import interface

T = TypeVar("T")
#: s: the input log goes out at most this long after an input (in batches, after the outputs)
INPUT_LOG_DELAY = 0.05
#: A jump of the wall clock against the monotonic one larger than this (seconds) is a step (NTP
#: steps at 0.128 s and slews below; a step this small moves nothing that matters)
CLOCK_STEP = 0.25
#: s: the wall clock is compared with the monotonic one only when both were read within this of
#: each other (a thread held between the reads, on a loaded host, is not a step of the clock)
CLOCK_READ = 0.01
#: s: a wake-up for a lease is armed this much after it expires (``Liveliness.expired`` is strict)
LEASE_SLACK = 0.001
DIAGNOSTICS_PERIOD = 1.0
#: s: a lease found expired is judged this much later, once: what the executor holds for the
#: unit by then (heartbeats that arrived in time and wait behind the wake-up, in a loaded unit)
#: is handled first
LEASE_SETTLE = 0.005
#: s: an EM that leaves (shuts down in order) is lost this long after its goodbye, unless the
#: unit shuts down meanwhile: a cell stopped with Ctrl-C, every process at once, records no fault.
EM_LEAVE_GRACE = 1.0


class UnitNode(GuardedNode):
    """One PackML unit. ``UnitNode(config)`` names itself ``config.name`` in ``/<config.cell>``."""

    def __init__(
        self,
        config: UnitConfig,
        *,
        context: Any = None,
        store_path: str | None = None,
        source: str | None = None,
        unit_lease: float | None = None,
        **node_kwargs: Any,
    ) -> None:
        namespace = node_kwargs.pop("namespace", f"/{config.cell}" if config.cell else "/")
        super().__init__(config.name, namespace=namespace, context=context, **node_kwargs)
        self.config = config
        self._declare_parameters(config, store_path)
        path = self.get_parameter("persistence_path").value
        try:
            self.store = Store(path, config.name) if path else None
        except StoreError:  # (StoreLocked too): no half-made node stays behind
            Node.destroy_node(self)
            raise
        self.clock = FrozenClock(self._now)
        self.unit = Unit(config, clock=self.clock, store=self.store)
        self.driver = UnitDriver(self.unit, self.clock, self._emit)
        self.liveliness = Liveliness(config.em_lease)
        #: which writer speaks for each EM (core.reports): a forger's reports are refused
        self.writers = Writers()
        self.refused_reports = 0
        self._log_limiter = LogLimiter()
        self._leaving: dict[str, tuple[float, EmReport]] = {}  # EM -> (when it is lost, goodbye)
        #: inputs not yet published: (time, index, name, arguments), made messages when they go out
        self._inputs: list[tuple[float, int, str, dict[str, Any]]] = []
        #: the wall clock's distance to the monotonic one when last read (a jump: a step)
        self._wall_offset: float | None = None
        self._input_index = 0
        self._record = bool(self.get_parameter("record_inputs").value)
        self.unit.on_input = self._on_input if self._record else None
        self._hardware_id = f"{config.cell}/{config.name}" if config.cell else config.name
        # the cell file as published on ~/config and recorded: never with its secrets
        # (its recipe files written in: the unit replays where they are not)
        inline = partial(inline_recipes, unit=config.name, book=config.recipes)
        self.source = redacted_yaml(source, transform=inline) if source is not None else None

        # liveliness: every face sees the unit gone within its lease (packml_ros2.presence)
        lease = unit_lease if unit_lease is not None else CoordinatorConfig.unit_lease
        publish = partial(interface.create_publisher, self)
        self.pub_status = publish("status", lease=lease)
        self.pub_transitions = publish("transitions")
        self.pub_admin = publish("admin")
        self.pub_alarms = publish("alarms")
        self.pub_inputs = publish("input_log")
        self.pub_diagnostics = publish("/diagnostics")
        self.pub_config = publish("config")
        self.pub_recipe = publish("recipe")
        self.pub_stack_light = publish("stack_light")
        self._outputs = {
            t.name: getattr(self, f"pub_{t.name}")
            for t in interface.topics(interface.Role.OUTPUT, interface.Role.DERIVED)
        }
        #: messages published per output topic: a snapshot says where a replay from it aligns
        self._published = dict.fromkeys(self._outputs, 0)
        # a recorder that joins gets the engine state: a replay starts from it (bag/replay.py)
        self.pub_snapshot = (
            publish(
                "snapshot",
                event_callbacks=PublisherEventCallbacks(matched=self._on_snapshot_matched),
            )
            if self._record
            else None
        )
        reports = interface.TOPIC["em_reports"]
        self._reports = self.create_subscription(
            reports.type, reports.path(), with_info(self._on_report), reports.qos
        )
        #: heartbeats on their own best-effort channel (qos.EM_HEARTBEATS), from the writer
        #: bound for each EM there (a forger cannot keep a dead EM alive)
        self.beat_writers = Writers()
        beats = interface.TOPIC["em_heartbeats"]
        self._beats = self.create_subscription(
            beats.type, beats.path(), with_info(self._on_heartbeat), beats.qos
        )
        self._create_services()
        # No polling: one timer, armed for the engine's next deadline, the next lease that can
        # expire, a goodbye's grace or the input log's batch (_arm after every callback).
        self._wake = self.create_timer(3600.0, self._on_wake)
        self._wake.cancel()
        self._wake_at: tuple[float, float] | None = None  # (engine due, steady due) armed
        #: steady time of the wake-up that judges a lease found expired (LEASE_SETTLE)
        self._settling: float | None = None
        self._timers = [
            self._wake,
            self.create_timer(DIAGNOSTICS_PERIOD, self._publish_diagnostics),
        ]
        if self.store is not None:  # the times since the last input survive a SIGKILL
            self._timers.append(self.create_timer(TIME_CHECKPOINT, self._checkpoint))
        self._closed = False
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.remote_lock = RemoteLock(
            self,
            config.name,
            config.remote_commands_enabled,
            lambda enabled: self._run(self.unit.set_remote_enabled, enabled),
        )
        self._publish_start()
        self._arm(self._time())
        self.get_logger().info(
            f"PackML unit {self.get_fully_qualified_name()} up: {state_name(self.unit.state)} in "
            f"{self.unit.mode_def.name}, {len(config.equipment_modules)} EM(s) configured"
            + (f", admin data from {path}" if path else ", no persistence")
        )

    # -- parameters --------------------------------------------------------------------------------
    def _declare_parameters(self, config: UnitConfig, store_path: str | None) -> None:
        self.declare_parameter(
            "persistence_path",
            store_path if store_path is not None else (config.persistence_path or ""),
            ParameterDescriptor(
                description="SQLite file for admin data ('' = none)", read_only=True
            ),
        )
        self.declare_parameter(
            "em_leave_grace",
            EM_LEAVE_GRACE,
            ParameterDescriptor(
                description="seconds between an EM's goodbye and its loss (no loss when the unit "
                "shuts down meanwhile, as when a whole cell is stopped)"
            ),
        )
        self.declare_parameter(
            "record_inputs",
            True,
            ParameterDescriptor(
                description="publish every engine input on ~/input_log", read_only=True
            ),
        )

    def _validate_parameters(self, params: list[Parameter[Any]]) -> SetParametersResult:
        for p in params:
            if p.name == "em_leave_grace" and not (
                p.type_ in (Parameter.Type.DOUBLE, Parameter.Type.INTEGER) and 0 <= p.value <= 60
            ):
                return SetParametersResult(
                    successful=False, reason="em_leave_grace must be 0 to 60 seconds"
                )
        return SetParametersResult(successful=True)

    # -- clock -------------------------------------------------------------------------------------
    def _now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def _time(self) -> float:
        """The engine's time now (the wall clock), after telling the engine of a step of that
        clock (NTP): the wall clock's distance to the monotonic clock jumped by more than
        :data:`CLOCK_STEP`. Slewing (NTP's small corrections) is followed without a step. Under
        simulated time a jump of /clock is time passing, not a step."""
        if self.uses_sim_time():
            return self._now()
        before = time.monotonic()
        now = self._now()
        after = time.monotonic()
        if after - before > CLOCK_READ:  # (the thread was held between the reads: no measure)
            return now
        offset = now - after
        last, self._wall_offset = self._wall_offset, offset
        if last is not None and abs(offset - last) > CLOCK_STEP:
            self.driver.clock_step(now, offset - last)
            self._flush_inputs()  # (a batch due on the old timeline goes out now)
        return now

    # -- services ----------------------------------------------------------------------------------
    def _create_services(self) -> None:
        """Every service :mod:`.ros.interface` declares (``set_remote_commands``: the remote lock)."""
        handlers: dict[str, Callable[[Any, Any], Any]] = {
            "command": self._srv_command,
            "set_mode": self._srv_set_mode,
            "reset_times": self._srv_reset_times,
            "reset_counters": self._srv_reset_counters,
            "ack_alarms": self._srv_ack_alarms,
            "reset_alarms": self._srv_reset_alarms,
            "query_alarms": self._srv_query_alarms,
            "set_alarm": self._srv_set_alarm,
            "set_mach_speed": self._srv_set_mach_speed,
            "set_unit_parameters": self._srv_set_parameters,
            "set_product": self._srv_set_product,
            "set_recipe": self._srv_set_recipe,
            "set_em_active": self._srv_set_em_active,
            "set_interlock": self._srv_set_interlock,
        }
        interface.create_services(self, handlers, self._srv_trigger, skip=[RemoteLock.SERVICE])

    def _answer(self, resp: Any, answer: Any, message_field: str = "message") -> Any:
        resp.accepted = answer.accepted
        resp.result = int(answer.reason)
        setattr(resp, message_field, answer.message + self._not_durable())
        return resp

    def _not_durable(self) -> str:
        """What an answer adds while the admin store cannot be written (a full disk)."""
        why = self.unit.not_durable
        return f" (not durable: {why})" if why else ""

    def _srv_command(self, req: Command.Request, resp: Command.Response) -> Command.Response:
        answer = self._run(self.unit.command, req.command, req.source or "operator")
        self._answer(resp, answer)
        resp.state_current = int(self.unit.state)
        resp.state_requested = int(self.unit.state_requested())
        return resp

    def _srv_trigger(
        self, cmd: Cmd, req: Trigger.Request, resp: Trigger.Response
    ) -> Trigger.Response:
        answer = self._run(self.unit.command, cmd, "operator")
        resp.success = answer.accepted
        resp.message = answer.message + self._not_durable()
        if answer.accepted and not answer.message.endswith(state_name(self.unit.state)):
            resp.message += f" (now {state_name(self.unit.state)})"
        return resp

    def _srv_set_mode(self, req: SetMode.Request, resp: SetMode.Response) -> SetMode.Response:
        mode: int | str = req.mode_name if req.mode_name else req.mode
        self._answer(resp, self._run(self.unit.set_mode, mode, req.source or "operator"))
        resp.mode_current = self.unit.mode
        return resp

    def _srv_reset_times(
        self, req: ResetTimes.Request, resp: ResetTimes.Response
    ) -> ResetTimes.Response:
        if req.scope not in (ResetTimes.Request.SCOPE_CURRENT_MODE, ResetTimes.Request.SCOPE_ALL):
            resp.accepted, resp.result = False, 13
            resp.message = f"scope {req.scope} is neither SCOPE_CURRENT_MODE (0) nor SCOPE_ALL (1)"
            return resp
        answer = self._run(
            self.unit.reset_times,
            req.scope == ResetTimes.Request.SCOPE_ALL,
            req.source or "operator",
        )
        return self._answer(resp, answer)

    def _srv_reset_counters(
        self, req: ResetCounters.Request, resp: ResetCounters.Response
    ) -> ResetCounters.Response:
        answer = self._run(self.unit.reset_counters, req.source or "operator")
        return self._answer(resp, answer)

    def _srv_ack_alarms(
        self, req: AckAlarms.Request, resp: AckAlarms.Response
    ) -> AckAlarms.Response:
        before = self.unit.alarms.unacknowledged_count()
        answer = self._run(
            self.unit.ack_alarms, None if req.all else req.id, req.value, req.source or "operator"
        )
        resp.acknowledged = before - self.unit.alarms.unacknowledged_count()
        return self._answer(resp, answer)

    def _srv_reset_alarms(
        self, req: ResetAlarms.Request, resp: ResetAlarms.Response
    ) -> ResetAlarms.Response:
        before = len(self.unit.alarms.current)
        answer = self._run(self.unit.reset_alarms, req.clear_first_out, req.source or "operator")
        resp.cleared = before - len(self.unit.alarms.current)
        return self._answer(resp, answer)

    def _srv_query_alarms(
        self, req: QueryAlarms.Request, resp: QueryAlarms.Response
    ) -> QueryAlarms.Response:
        events = self.unit.alarms.query(
            active_only=req.active_only,
            category=req.category if req.filter_category else None,
            sort=convert.QUERY_SORTS.get(req.sort, "time"),
            include_warnings=req.include_warnings,
            history=req.history,
        )
        resp.alarms = [convert.alarm(ev) for ev in events]
        resp.count = len(events)
        return resp

    def _srv_set_alarm(self, req: SetAlarm.Request, resp: SetAlarm.Response) -> SetAlarm.Response:
        answer = self._run(
            self.unit.set_alarm,
            req.id,
            req.value,
            req.active,
            req.source or "operator",
            "",
            req.warning or None,
            req.category,
            req.message,
        )
        return self._answer(resp, answer, "message_out")

    def _srv_set_mach_speed(
        self, req: SetMachSpeed.Request, resp: SetMachSpeed.Response
    ) -> SetMachSpeed.Response:
        answer = self._run(self.unit.set_mach_speed, req.mach_speed, req.source or "operator")
        resp.mach_speed = self.unit.mach_speed
        return self._answer(resp, answer)

    def _srv_set_parameters(
        self, req: SetUnitParameters.Request, resp: SetUnitParameters.Response
    ) -> SetUnitParameters.Response:
        answer = self._run(
            self.unit.set_parameters,
            [convert.descriptor_in(d) for d in req.parameter],
            req.source or "operator",
        )
        return self._answer(resp, answer)

    def _srv_set_product(
        self, req: SetProduct.Request, resp: SetProduct.Response
    ) -> SetProduct.Response:
        answer = self._run(
            self.unit.set_product,
            [convert.product_in(p) for p in req.product],
            req.source or "operator",
        )
        return self._answer(resp, answer)

    def _srv_set_recipe(self, req: Any, resp: Any) -> Any:
        answer = self._run(
            self.unit.set_recipe, req.recipe_id, req.recipe_name[:255], req.source or "operator"
        )
        return self._answer(resp, answer)

    def _srv_set_em_active(
        self, req: SetEmActive.Request, resp: SetEmActive.Response
    ) -> SetEmActive.Response:
        answer = self._run(self.unit.set_em_active, req.em, req.active, req.source or "operator")
        return self._answer(resp, answer)

    def _srv_set_interlock(
        self, req: SetInterlock.Request, resp: SetInterlock.Response
    ) -> SetInterlock.Response:
        answer = self._run(self.unit.set_interlock, req.active, req.reason, req.source)
        return self._answer(resp, answer)

    # -- equipment modules -------------------------------------------------------------------------
    def _on_report(self, msg: EmReport, info: MessageInfo) -> None:
        """An EM report: checked field by field, and taken only from the writer that speaks for
        its EM (core.reports); then applied (driver.report), a goodbye after a grace."""
        now, tick = self._time(), self.steady()  # (engine time; the leases' clock)
        problem = report_problem(msg, self.unit.sequence)
        if problem is not None:
            self.refused_reports += 1
            self.unit.stats.bad_reports += 1
            self._log("warn", f"EM report refused: {problem}")
            return
        gid = info.get("publisher_gid")
        writer = bytes(gid["data"]) if gid else b""
        taken, note = self.writers.claim(msg.em, writer, tick, self._writer_gone)
        if note is not None:
            self._log("warn" if not taken else "info", note)
        if not taken:
            self.refused_reports += 1
            return
        leaving = msg.kind == LEAVE
        if leaving or msg.em not in self.unit.equipment.modules:
            self.writers.release(msg.em)  # left, or not an EM of the unit: keep nothing
            self.beat_writers.release(msg.em)
        if leaving:
            self._leave(msg, now, tick)
        else:
            self._leaving.pop(msg.em, None)  # anything else from it: it is back (or never left)
            self.driver.report(now, msg, self.liveliness, tick)
        self._arm(now)

    def _on_heartbeat(self, msg: EmReport, info: MessageInfo) -> None:
        """A heartbeat on the best-effort channel: it renews the EM's lease however long a
        reliable report ahead of it on ``em_reports`` waits for its repair (a network blip
        shorter than the lease never loses an EM). Nothing but heartbeats is taken here."""
        tick = self.steady()  # a heartbeat only renews a lease: the leases' clock
        problem = report_problem(msg, self.unit.sequence)
        if problem is None and msg.kind != EmReport.KIND_HEARTBEAT:
            problem = f"a report of kind {msg.kind} on em_heartbeats (only heartbeats go there)"
        if problem is not None:
            self.refused_reports += 1
            self.unit.stats.bad_reports += 1
            self._log("warn", f"EM heartbeat refused: {problem}")
            return
        if msg.em not in self.unit.equipment.modules or msg.em in self._leaving:
            return  # (registration and goodbyes go by em_reports, in order)
        gid = info.get("publisher_gid")
        writer = bytes(gid["data"]) if gid else b""
        taken, note = self.beat_writers.claim(msg.em, writer, tick, self._beat_writer_gone)
        if note is not None and not taken:
            self._log("warn", note)
        if not taken:
            self.refused_reports += 1
            return
        if msg.em in self.liveliness.alive:  # (the wake-up due at the old expiry re-arms)
            self.liveliness.seen(msg.em, tick)

    def _beat_writer_gone(self, writer: bytes) -> bool:
        return self._writer_gone(writer, self._beats.topic_name)

    def _leave(self, msg: EmReport, now: float, tick: float) -> None:
        """An EM's goodbye counts after a grace: when a whole cell is stopped (Ctrl-C under
        ros2 launch: every process gets SIGINT at once), its EMs' goodbyes can arrive before
        this process notices its own signal; its shutdown then drops them (no false fault)."""
        if not run.shutting_down():
            grace = float(self.get_parameter("em_leave_grace").value)
            self._leaving[msg.em] = (tick + grace, msg)
            if grace <= 0:
                self._apply_leaves(now, tick)

    def _apply_leaves(self, now: float, tick: float) -> None:
        for name, (due, msg) in list(self._leaving.items()):
            if due <= tick:
                del self._leaving[name]
                self.driver.report(now, msg, self.liveliness, tick)

    def _writer_gone(self, writer: bytes, topic: str = "") -> bool:
        """Whether ``writer`` no longer publishes EM reports here (its node or process ended)."""
        topic = topic or self._reports.topic_name
        return all(
            bytes(bytearray(e.endpoint_gid))[: len(writer)] != writer
            for e in self.get_publishers_info_by_topic(topic)
        )

    def _on_wake(self) -> None:
        if self._closed:
            return  # closed while this wake-up waited (a test's multi-threaded executor): no timer
        self._wake_at = None  # fired: _arm sets it again
        self._wake.cancel()
        if run.shutting_down():
            return  # this process is stopping: EMs going silent now are no news
        now, tick = self._time(), self.steady()
        self._apply_leaves(now, tick)
        # A lease that ran out is judged LEASE_SETTLE later, after what waits in the executor's
        # queue (a heartbeat that arrived in time renews it); the wake-up reads no topic itself
        if self.liveliness.next_expiry() >= tick:
            self._settling = None
        elif self._settling is None:
            self._settling = tick + LEASE_SETTLE
        if self._settling is not None and tick >= self._settling:
            self._settling = None
            for name, lease in self.liveliness.expired(tick):
                self.writers.release(name)
                self.beat_writers.release(name)
                self._leaving.pop(name, None)
                self.driver.call(now, self.unit.em_lost, name, f"no report for {lease:g} s")
        summary = self._log_limiter.due(tick)
        if summary is not None:
            self.get_logger().warning(summary)
        self.driver.catch_up(now)
        self._flush_inputs()
        self._arm(now)

    def _arm(self, now: float) -> None:
        """Arm the wake-up timer for the next thing due (nothing: no timer runs). The engine's
        deadlines and the input log's batch are due in engine time (``now``); leases and
        goodbyes on the steady clock, so a step of the wall clock neither expires them nor
        holds them off."""
        due = self.unit.deadlines.next_due
        if self._inputs:  # the batch goes out INPUT_LOG_DELAY after its first input: a due
            # time that inputs do not move, so the EMs' reports do not reset the timer one by one
            due = min(due, self._inputs[0][0] + INPUT_LOG_DELAY)
        steady_due = self.liveliness.next_expiry() + LEASE_SLACK
        if self._settling is not None:
            steady_due = min(steady_due, self._settling)
        for leave_at, _ in self._leaving.values():
            steady_due = min(steady_due, leave_at)
        if (due, steady_due) == self._wake_at or self._closed:
            return
        self._wake_at = (due, steady_due)
        if due == math.inf and steady_due == math.inf:
            self._wake.cancel()
            return
        delay = min(due - now, steady_due - self.steady())
        self._wake.timer_period_ns = max(int(delay * 1e9), 1)
        self._wake.reset()

    # -- publishing --------------------------------------------------------------------------------
    def _run(self, fn: Callable[..., T], *args: Any) -> T:
        """An input from a service or parameter callback, at the node's time now."""
        now = self._time()
        try:
            return self.driver.call(now, fn, *args)
        finally:
            self._arm(now)

    def _emit(self, topic: str, msg: Any) -> None:
        if topic == "log":
            self._log(*msg)
            return
        if not self.context.ok():
            return  # Ctrl-C arrived while a callback ran: the publishers are gone
        self._outputs[topic].publish(msg)
        self._published[topic] += 1
        if topic == "alarms":
            self._publish_diagnostics()
        if len(self._inputs) >= 200:
            self._flush_inputs()

    def _publish_start(self) -> None:
        """What a recording needs to replay this unit: the cell configuration (latched ~/config)
        and a first input ``start`` with the admin data the unit restored, its start time and
        whether it has a persistence store; then the start-up
        outputs (the RESTART transition and its status, the admin data)."""
        if self.source is not None:
            self.pub_config.publish(
                String(data=json.dumps({"unit": self.config.name, "cell_yaml": self.source}))
            )
        if self._record:
            # "persistence": whether the unit has a store (its periodic saves are deadlines too,
            # so replay needs one exactly when the node had one)
            start = {
                "document": self.unit.restored,
                "time": self.unit.now,
                "persistence": self.store is not None,
                "schema": inputlog.SCHEMA,
            }
            # (a copy: the input goes out later, and the engine keeps the restored document)
            self._on_input(self.unit.now, inputlog.START, json.loads(json.dumps(start)))
        self._emit("stack_light", self.driver.stack_light_message())
        self.driver.flush()
        self._emit("admin", self.driver.admin_message())

    def _on_snapshot_matched(self, info: QoSPublisherMatchedInfo) -> None:
        if info.current_count_change > 0 and not self._closed:
            self.publish_snapshot()

    def publish_snapshot(self) -> None:
        """The engine state now (between inputs: the node's callbacks are mutually exclusive),
        after input ``index``, with what replay needs besides it."""
        if self.pub_snapshot is None or not self.context.ok():
            return
        msg = self.driver.snapshot_message(
            self._input_index, self._published, self.store is not None
        )
        self.pub_snapshot.publish(msg)

    def _log(self, level: str, text: str) -> None:
        """A log line of the engine or the node: callers' text escaped (no forged lines), repeated
        lines rate-limited (core.limits)."""
        write, summary = self._log_limiter.admit(text, self.steady())
        if summary is not None:
            self.get_logger().warning(summary)
        if not write:
            return
        text = printable(text, 1000)
        # rclpy ties a severity to each call site: one call per level.
        if level == "warn":
            self.get_logger().warning(text)
        else:
            self.get_logger().info(text)

    def _checkpoint(self) -> None:
        if not self._closed:
            self.unit.checkpoint(self._time())

    def _publish_diagnostics(self) -> None:
        unit = self.unit
        view = unit.status()
        self.pub_diagnostics.publish(
            convert.diagnostics(self.config.name, self._hardware_id, unit.now, view, unit.alarms)
        )

    def _on_input(self, t: float, name: str, args: dict[str, Any]) -> None:
        """An input the engine applied, kept for the input log. Its message is made when the
        batch goes out (after the statuses, off the path of a command and of the EMs' reports:
        a fifth of the unit's work per report); the arguments are the engine's own, made for
        this record and not kept by it."""
        self._input_index += 1
        self._inputs.append((t, self._input_index, name, args))

    def _flush_inputs(self) -> None:
        """The input log goes out in batches (every tick, 50 ms), never delaying a status; the
        order is kept and every message carries its index."""
        inputs, self._inputs = self._inputs, []
        if not self.context.ok():
            return  # shutting down: nobody can receive them any more
        unit, publish = self.config.name, self.pub_inputs.publish
        for t, index, name, args in inputs:
            publish(
                convert.build(
                    UnitInput,
                    stamp=convert.stamp(t),
                    index=index,
                    unit=unit,
                    name=name,
                    args_json=json.dumps(args, separators=(",", ":")),
                )
            )

    def close(self) -> None:
        """Record the unit's shutdown (an event; the StopReason when it was producing), publish
        it, stop the timers and save a last time (idempotent); destroy_node calls it too."""
        if self._closed:
            return
        self._closed = True
        for timer in self._timers:
            self.destroy_timer(timer)
        self._leaving.clear()  # goodbyes of EMs that stop with this unit: no loss
        reason = run.shutdown_reason() or "node closed"
        self._run(self.unit.shutdown, reason)  # publishes only while the context is up
        self._flush_inputs()
        self.unit.close()
        self.unit.store = None  # a callback still running after this must not touch the file
        if self.context.ok():
            saved = f"; admin data saved to {self.store.path}" if self.store else ""
            if self.unit.not_durable:
                saved = f"; admin data NOT saved ({self.unit.not_durable})"
            self.get_logger().info(
                f"PackML unit {self.get_fully_qualified_name()} shut down ({reason}) in "
                f"{state_name(self.unit.state)}{saved}"
            )

    def destroy_node(self) -> None:
        self.close()
        super().destroy_node()


def pick_unit(cell: CellConfig, cell_file: str, unit: str | None) -> UnitConfig:
    if unit is None:
        if len(cell.units) != 1:
            raise SystemExit(
                f"{cell_file} has units {', '.join(cell.units)}: name one (unit_node <cell.yaml> <unit>)"
            )
        return next(iter(cell.units.values()))
    if unit not in cell.units:
        raise SystemExit(f"{cell_file} has no unit {unit!r} (units: {', '.join(cell.units)})")
    return cell.units[unit]


def main(argv: Sequence[str] | None = None) -> int:
    args = run.init(argv)
    if not args or args[0] in ("-h", "--help"):
        print(__doc__)
        print(interface.describe())
        return 0 if args else 2
    try:
        cell = load_cell(args[0])
        config = pick_unit(cell, args[0], args[1] if len(args) > 1 else None)
        if config.plc is not None:
            raise ValueError(
                f"{config.name} is a PLC unit (plc:): run plc_bridge {args[0]} {config.name}"
            )
        source = Path(args[0]).read_text(encoding="utf-8")
    except ConfigError as exc:
        print(exc.prefixed("unit_node"), file=sys.stderr)
        return 2
    except Exception as exc:  # one readable message, exit 2
        print(f"unit_node: {exc}", file=sys.stderr)
        return 2
    try:
        node = UnitNode(config, source=source, unit_lease=cell.coordinator.unit_lease)
    except StoreError as exc:
        print(f"unit_node: {exc}", file=sys.stderr)
        return 2
    return run.spin([node], on_shutdown=node.close)


if __name__ == "__main__":
    sys.exit(main())
