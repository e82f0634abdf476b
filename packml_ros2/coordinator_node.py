"""The cell coordinator: the ISA-88 "procedure" level above the units of a cell (docs/packml.md §4),
and the line's performance (stop episodes, losses, OEE per shift).

Node ``/<cell>/coordinator``, a thin shell around :class:`packml_ros2.core.line.Line` (the logic:
units, their order on the line, cell commands, aggregation, interlock propagation, episodes and
losses; see :mod:`packml_ros2.core.line.cell`, :mod:`~packml_ros2.core.line.sequence`,
:mod:`~packml_ros2.core.line.performance`). Services: ``command`` (packml_interfaces/Command),
``set_mode`` (SetMode) and the Trigger shortcuts ``reset`` ... ``complete``, fanned out to the
units through their remote path (source ``remote:coordinator``: a unit accepts it only while its
parameter ``remote_commands_enabled`` is true); ``line/query_episodes`` (QueryEpisodes),
``line/query_losses`` (QueryLosses), ``line/reset_losses`` (Trigger). Topics: ``status``
(CellStatus, latched, DDS liveliness with lease ``unit_lease`` like the units' status, on
every change), ``line/episodes`` (LineEpisode, every change of an episode), ``line/losses`` (LineLosses, every ``line.publish_period``), ``line/input_log``
(UnitInput: what the line's performance was given, for ``packml record``/``replay``),
``line/snapshot`` (UnitSnapshot: the line's state, published when a subscriber (a recorder) joins:
a recording that begins after more inputs than the input log keeps replays from it).

The service handlers block while a sequence runs: spin the node with a MultiThreadedExecutor
(``main`` does).

Run: ``coordinator <cell.yaml>`` or ``python -m packml_ros2.coordinator_node <cell.yaml>``.
"""

from __future__ import annotations

import json
import math
import sys
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from functools import partial
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from packml_interfaces.msg import (
    CellStatus,
    LineEpisode,
    LineLosses,
    Result,
    UnitInput,
    UnitSnapshot,
    UnitSummary,
)
from packml_interfaces.srv import Command, QueryEpisodes, QueryLosses, SetMode
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.event_handler import PublisherEventCallbacks, QoSPublisherMatchedInfo
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from std_srvs.srv import Trigger

from . import line_msgs, qos, responses, run
from .boundary import GuardedNode
from .client import UnitProxy
from .core import CellConfig, Cmd, ConfigError, State, load_cell, state_name, unit_config
from .core.line.cell import (
    INTERLOCK_SOURCE,
    SEVERITY,
    SOURCE,
    Call,
    Effect,
    Log,
    Resubscribe,
    aggregate_state,
    interlock_failure,
)
from .core.line.line import Line
from .core.line.sequence import POLL, START_LIKE, STOP_LIKE, Answer, Outcome, Run, StopWaits
from .core.line.store import LineStore
from .core.numbers import command_name
from .core.persistence import StoreError
from .core.rules import rules_of

__all__ = [
    "INTERLOCK_SOURCE",
    "SEVERITY",
    "SOURCE",
    "START_LIKE",
    "STOP_LIKE",
    "TARGET",
    "CoordinatorNode",
    "aggregate_state",
    "main",
]

#: The wait state each command leads to in the default model (the rule book's): the cell's
#: ``state_requested`` in a Command answer.
TARGET: dict[Cmd, State] = {
    c: t for c in Cmd if c and (t := rules_of(unit_config()).command_target(c)) is not None
}
#: s: a call the coordinator could not send (the unit's service not discovered yet) is tried again
CALL_RETRY = 0.1
THREADS = 8  # executor threads of main(): sequences block one each, callbacks need the rest


class CoordinatorNode(GuardedNode):
    """The coordinator of ``cell``: node ``coordinator`` in ``/<cell>``. Raises
    :class:`~packml_ros2.core.persistence.StoreError` when the line's store cannot be opened."""

    def __init__(self, cell: CellConfig, **node_kwargs: Any) -> None:
        namespace = node_kwargs.pop("namespace", f"/{cell.cell}")
        super().__init__("coordinator", namespace=namespace, **node_kwargs)
        self.cell = cell
        self.config = cell.coordinator
        self._cond = threading.Condition(threading.RLock())
        self._group = ReentrantCallbackGroup()
        try:
            store = LineStore(cell.line.store, cell.cell) if cell.line.store else None
        except StoreError:  # (StoreLocked too): no half-made node stays behind
            Node.destroy_node(self)
            raise
        self.line = Line(cell, time.monotonic, self._wall, store)
        for problem in store.problems if store else ():
            self.get_logger().warning(f"line store: {problem}")
        self._report_interrupted()
        self._proxies = {
            name: UnitProxy(self, f"/{cell.cell}/{name}", self._on_unit) for name in cell.units
        }
        self._last_msg: CellStatus | None = None
        self._closed = False
        self._not_durable = ""  # why the line's store cannot be written now ('' = it can)
        self._flight: dict[str, Any] | None = None  # the cell command in flight (line store)

        # with the units' liveliness lease: faces see a coordinator that is gone within it
        # (packml_ros2.presence); subscribers with the default QoS are unaffected
        self.pub_status = self.create_publisher(
            CellStatus, "~/status", qos.with_lease(qos.CELL_STATUS, self.config.unit_lease)
        )
        self.pub_inputs = self.create_publisher(UnitInput, "~/line/input_log", qos.LINE_INPUT_LOG)
        self.pub_episodes = self.create_publisher(LineEpisode, "~/line/episodes", qos.LINE_EPISODES)
        self.pub_losses = self.create_publisher(LineLosses, "~/line/losses", qos.LINE_LOSSES)
        self._published = {"episodes": 0, "losses": 0}  # what a snapshot says was published
        self.pub_snapshot = self.create_publisher(
            UnitSnapshot,
            "~/line/snapshot",
            qos.SNAPSHOT,
            event_callbacks=PublisherEventCallbacks(matched=self._on_snapshot_matched),
        )
        # (one message at a time, in order: a unit's stale and fresh entries must not swap, as
        # the units' topics must not: UnitProxy)
        self.create_subscription(
            DiagnosticArray,
            "/diagnostics",
            self._on_diagnostics,
            qos.DIAGNOSTICS,
            callback_group=MutuallyExclusiveCallbackGroup(),
            event_callbacks=qos.quiet_events(),
        )
        serve = partial(responses.create_service, self, callback_group=self._group)
        serve(Command, "~/command", self._srv_command)
        serve(SetMode, "~/set_mode", self._srv_set_mode)
        for verb, cmd in responses.TRIGGER_SHORTCUTS:
            serve(Trigger, f"~/{verb}", partial(self._srv_trigger, cmd))
        serve(QueryEpisodes, "~/line/query_episodes", self._srv_episodes)
        serve(QueryLosses, "~/line/query_losses", self._srv_losses)
        serve(Trigger, "~/line/reset_losses", self._srv_reset_losses)
        # No polling: one timer, armed for the next thing due (Line.next_due: a lease, a retry,
        # the losses' publication) after every callback (_arm, in _flush).
        self._timer = self.create_timer(3600.0, self._on_tick, callback_group=self._group)
        self._timer.cancel()
        self._due = math.inf
        self._retry_calls = False  # a call was not sent: try again after CALL_RETRY
        if self.config.unit_lease <= 1.0:
            self.get_logger().warning(
                f"unit_lease {self.config.unit_lease:g} s is not longer than the units' 1 s "
                "diagnostics period: idle units will flap between online and lost"
            )
        with self._cond:
            self._flush()
        c = self.line.cell
        self.get_logger().info(
            f"coordinator of {cell.cell} up: units {', '.join(cell.units)}; start order "
            f"{' > '.join(c.start_order)}, stop order {' > '.join(c.stop_order)}; line "
            f"{' > '.join(self.line.perf.order)} (output {self.line.perf.output}); unit lease "
            f"{self.config.unit_lease:g} s, step timeout {self.config.step_timeout:g} s"
        )

    def _wall(self) -> int:
        return int(self.get_clock().now().nanoseconds)

    # ==============================================================================================
    # What arrives
    # ==============================================================================================
    def _on_unit(self, path: str, topic: str, msg: Any) -> None:
        name = path.rsplit("/", 1)[-1]
        with self._cond:
            if self._closed:
                return
            news, effects = self.line.on_unit(name, topic, msg)
            if news:
                self._cond.notify_all()
            self._apply(effects)
            self._flush()

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        with self._cond:
            if self._closed:
                return
            changed = False
            for entry in msg.status:
                name = self.line.cell.hardware_ids.get(entry.hardware_id)
                if name is not None and entry.name == f"packml: {name}":
                    stale = entry.level == DiagnosticStatus.STALE
                    news, effects = self.line.on_diagnostics(name, stale, entry.message)
                    changed |= news
                    self._apply(effects)
            if changed:
                self._cond.notify_all()
                self._flush()
            else:
                self._arm()  # (a lost unit's diagnostics ask for a new subscription)

    def _on_tick(self) -> None:
        with self._cond:
            self._timer.cancel()
            self._due = math.inf  # fired: _arm sets it again
            if self._closed:
                return
            self._retry_calls = False
            effects = self.line.tick()
            again = [e.unit for e in effects if isinstance(e, Resubscribe)]
            self._apply(effects)
            at, views = self.line.losses_due()
            for view in views:
                self.pub_losses.publish(
                    line_msgs.losses_msg(view, self.cell.cell, at, self._designs())
                )
                self._published["losses"] += 1
            self._cond.notify_all()
            self._flush()
        for name in again:  # outside the lock: creating subscriptions takes the node's locks
            self._proxies[name].resubscribe("status", "transitions")

    def _designs(self) -> dict[str, float]:
        return {s: self.line.perf.design(s) for s in ("", *self.line.perf.order)}

    # ==============================================================================================
    # Effects and publications (lock held)
    # ==============================================================================================
    def _apply(self, effects: list[Effect]) -> None:
        log = self.get_logger()
        for e in effects:
            if isinstance(e, Log) and e.level == "warning":  # rclpy: one call site per level
                log.warning(e.text)
            elif isinstance(e, Log):
                log.info(e.text)
            elif isinstance(e, Call):
                proxy = self._proxies[e.unit]
                if not proxy.client(e.service).service_is_ready():
                    self._retry_calls = True  # not discovered yet (or gone): try again soon
                    continue
                if e.purpose == "interlock":
                    self.line.interlock_sending(e)
                    future = proxy.call(e.service, **e.fields)
                    future.add_done_callback(
                        partial(self._interlock_done, e.unit, bool(e.fields["active"]), e.why)
                    )
                else:
                    future = proxy.call(e.service, **e.fields)
                    future.add_done_callback(partial(self._reacted, e.why))

    def _interlock_done(self, unit: str, want: bool, reason: str, future: Future[Any]) -> None:
        exc = future.exception()
        error = None
        if exc is not None:
            error = str(exc) or type(exc).__name__
        else:
            a = future.result()
            error = interlock_failure(want, a.accepted, a.result, a.message)
        with self._cond:
            if self._closed:
                return
            self._apply(self.line.interlock_done(unit, want, reason, error))
            self._flush()

    def _reacted(self, why: str, future: Future[Any]) -> None:
        exc = future.exception()
        answer = exc if exc is not None else future.result().message
        self.get_logger().info(f"{why}: {answer}")

    def _flush(self) -> None:
        """Publish what the line has to say: its inputs, changed episodes, the cell status."""
        records, episodes = self.line.take()
        for r in records:
            self.pub_inputs.publish(
                UnitInput(
                    stamp=line_msgs.stamp(r.t),
                    index=r.index,
                    unit=r.unit,
                    name=r.name,
                    args_json=r.args_json,
                )
            )
        for view in episodes:
            self.pub_episodes.publish(line_msgs.episode_msg(view, self.cell.cell))
            self._published["episodes"] += 1
        self._persistence()
        self._publish()
        self._arm()

    def _persistence(self) -> None:
        """Log when the line's store starts or stops failing (a full disk: the coordinator runs
        on, holds what it could not write and writes it with the next commit that succeeds)."""
        store = self.line.store
        failing = store.failing if store is not None else ""
        if failing == self._not_durable:
            return
        if failing and not self._not_durable:
            self.get_logger().error(
                f"line store: persistence failing: {failing}; the line's losses since are held in memory, not durable (retried at each input)"
            )
        elif not failing:
            self.get_logger().info(
                "line store: persistence recovered: the held losses are on the disk"
            )
        self._not_durable = failing

    def _durability_note(self) -> str:
        return f" (not durable: {self._not_durable})" if self._not_durable else ""

    def _on_snapshot_matched(self, info: QoSPublisherMatchedInfo) -> None:
        """A subscriber (a recorder) joined: the line's state now, after what was published."""
        if info.current_count_change <= 0:
            return
        with self._cond:
            if self._closed or not self.context.ok():
                return
            self._flush()
            index, t, doc = self.line.snapshot(self._published)
            self.pub_snapshot.publish(
                UnitSnapshot(
                    stamp=line_msgs.stamp(t),
                    index=index,
                    unit="",
                    state_json=json.dumps(doc, separators=(",", ":")),
                )
            )

    def _arm(self) -> None:
        """Arm the timer for the next thing due (nothing: no timer runs; lock held)."""
        if self._closed:
            return
        now = time.monotonic()
        due = self.line.next_due()
        if self._retry_calls:
            due = min(due, now + CALL_RETRY)
        due = max(due, now)
        if due >= self._due:
            return  # armed for sooner: when it fires, it arms for what is due then
        self._due = due
        self._timer.timer_period_ns = max(int((due - now) * 1e9), 1)
        self._timer.reset()

    def _summary(self, u: Any) -> UnitSummary:
        out = UnitSummary(name=u.name, online=u.online, health=u.health)
        s = u.status
        if s is not None:
            out.state_current = s.state_current
            out.state_current_name = s.state_current_name
            out.unit_mode_current = s.unit_mode_current
            out.unit_mode_current_name = s.unit_mode_current_name
            out.sequence = s.sequence
            out.remote_commands_enabled = s.remote_commands_enabled
            out.em_total = u.em_total
            out.em_online = u.em_online
            out.active_alarms = s.active_alarms
            out.alarm_banner = s.alarm_banner
            out.blocked = s.equipment_interlock.blocked
            out.starved = s.equipment_interlock.starved
            out.interlock_suspended = u.interlock_suspended
        else:
            out.state_current_name = state_name(State.UNDEFINED)
        return out

    def _publish(self) -> None:
        """Publish the cell status if anything but the stamp changed (lock held)."""
        v = self.line.view()
        msg = CellStatus(
            cell=v.cell,
            units=[self._summary(u) for u in v.units],
            state_current=v.state_current,
            state_current_name=state_name(v.state_current),
            unit_mode_current=v.unit_mode_current,
            all_online=v.all_online,
            busy=v.busy,
            sequence_step=v.sequence_step,
            lost_units=list(v.lost_units),
            detail=v.detail + self._durability_note(),
            commands_valid=list(v.commands_valid),
            commands_valid_names=[command_name(c) for c in v.commands_valid],
        )
        previous = self._last_msg
        if previous is not None:
            msg.stamp = previous.stamp
            if msg == previous:
                return
        msg.stamp = self.get_clock().now().to_msg()
        self._last_msg = msg
        self.pub_status.publish(msg)

    @property
    def cell_status(self) -> CellStatus | None:
        """The last published cell status."""
        with self._cond:
            return self._last_msg

    # ==============================================================================================
    # Runs: cell commands and mode changes
    # ==============================================================================================
    def _ready(self, unit: str, service: str) -> bool:
        return bool(self._proxies[unit].client(service).service_is_ready())

    def _drive(self, run: Run) -> Outcome:
        """Carry out ``run`` until it has its outcome (this thread blocks; lock held)."""
        while True:
            step = run.next(time.monotonic(), self._ready)
            self._flush()
            if isinstance(step, Outcome):
                return step
            calls, wait = step
            for call in calls:
                # kept before it is sent: a coordinator killed before the answer arrives still
                # says the unit may have acted on it
                self._in_flight_reached(call.unit)
                future = self._proxies[call.unit].call(call.service, **call.fields)
                future.add_done_callback(partial(self._answered, run, call.unit, call.service))
            self._cond.wait(min(wait, POLL))

    def _answered(self, run: Run, unit: str, service: str, future: Future[Any]) -> None:
        exc = future.exception()
        if exc is not None:
            answer = Answer(error=str(exc) or type(exc).__name__)
        else:
            r = future.result()
            answer = Answer(
                bool(r.accepted),
                int(r.result),
                str(r.message),
                int(getattr(r, "state_current", 0)),
                int(getattr(r, "state_requested", 0)),
            )
        with self._cond:
            run.answer(unit, service, answer)
            self._cond.notify_all()

    # -- the cell command in flight, kept in the line store (issue 25): a coordinator killed in
    # the middle of one says after its restart which command it was and which units it had
    # reached, and never resumes it (a restart sets no machine in motion)
    def _in_flight(self, command: str, caller: str) -> None:
        self._flight = {"command": command, "caller": caller, "since": time.time(), "reached": []}
        self._keep_flight()

    def _in_flight_reached(self, unit: str) -> None:
        flight = self._flight
        if flight is not None and unit not in flight["reached"]:
            flight["reached"].append(unit)
            self._keep_flight()

    def _in_flight_end(self) -> None:
        self._flight = None
        self._keep_flight()

    def _keep_flight(self) -> None:
        if self.line.store is not None:
            self.line.store.note("command", self._flight)

    def _report_interrupted(self) -> None:
        """At start: a cell command the last coordinator did not finish, said (log, the cell
        status's detail) and forgotten; nothing is sent to the units."""
        store = self.line.store
        flight = store.noted("command") if store is not None else None
        if flight is None:
            return
        reached = [u for u in flight.get("reached", []) if isinstance(u, str)][:64]
        others = [u for u in self.cell.units if u not in reached]
        when = time.strftime("%H:%M:%S", time.localtime(float(flight.get("since", 0) or 0)))
        text = (
            f"{str(flight.get('command'))[:20]} from {str(flight.get('caller'))[:80]} at {when} was "
            f"interrupted (the coordinator ended): it had reached {', '.join(reached) or 'no unit'}"
            f"{'; not ' + ', '.join(others) if others else ''}; not resumed"
        )
        self.get_logger().warning(f"cell command {text}")
        self.line.last_result = text
        if store is not None:
            store.note("command", None)

    def _not_blocking_executor(self) -> str:
        """Why the handlers may not block here ('' = they may)."""
        if isinstance(self.executor, MultiThreadedExecutor):
            return ""
        return (
            "the coordinator must be spun by a MultiThreadedExecutor (its services wait for the "
            "units while their status keeps arriving)"
        )

    def cell_command(self, cmd: int, caller: str = "operator") -> tuple[bool, int, str]:
        """Run cell command ``cmd`` (blocks until the sequence ended): (accepted, result, message)."""
        if not 1 <= cmd <= 10:
            return False, Result.UNKNOWN_COMMAND, f"command {cmd} is not a PackML command (1..10)"
        problem = self._not_blocking_executor()
        if problem:
            return False, Result.UNIT_UNAVAILABLE, problem
        command = Cmd(cmd)
        started = time.monotonic()
        with self._cond:
            begun = self.line.begin_command(command, caller)
            while isinstance(begun, StopWaits):  # the core cancelled the sequence: it ends soon
                self._cond.notify_all()
                self._cond.wait(begun.poll)  # (woken when a run ends)
                begun = self.line.begin_command(command, caller, begun.since)
            if isinstance(begun, Outcome):
                outcome = begun
            else:
                run_id, run = begun
                self._in_flight(command.name, caller)
                try:
                    outcome = self._drive(run)
                finally:
                    self.line.end(run_id)
                    self._in_flight_end()
                    self._cond.notify_all()  # a STOP waiting for this run begins
            text = f"{command.name} from {caller}: {outcome.message}"
            if outcome.accepted:  # rclpy ties a severity to each call site: one call per level
                self.get_logger().info(text)
            else:
                self.get_logger().warning(text)
            self.line.last_result = f"{command.name} {'done' if outcome.accepted else 'failed'} ({time.monotonic() - started:.1f} s)"
            self._flush()
        return outcome.accepted, outcome.result, outcome.message

    def cell_set_mode(
        self, mode: int, mode_name: str = "", caller: str = "operator"
    ) -> tuple[bool, int, str, int]:
        """A mode change of every unit, all or nothing (:class:`~packml_ros2.core.line.sequence.ModeRun`):
        (accepted, result, message, mode): the new mode, or the mode the cell had (0: mixed)."""
        problem = self._not_blocking_executor()
        if problem:
            return False, Result.UNIT_UNAVAILABLE, problem, 0
        with self._cond:
            begun = self.line.begin_mode(mode, mode_name)
            if isinstance(begun, Outcome):
                if not begun.busy:
                    self.get_logger().warning(f"from {caller}: {begun.message}")
                return begun.accepted, begun.result, begun.message, begun.mode
            run_id, run = begun
            try:
                outcome = self._drive(run)
            finally:
                self.line.end(run_id)
                self._flush()
                self._cond.notify_all()
            if outcome.accepted:
                self.get_logger().info(f"from {caller}: {outcome.message}")
            else:
                self.get_logger().warning(f"from {caller}: {outcome.message}")
        return outcome.accepted, outcome.result, outcome.message, outcome.mode

    # ==============================================================================================
    # Services
    # ==============================================================================================
    def _srv_command(self, req: Command.Request, resp: Command.Response) -> Command.Response:
        resp.accepted, resp.result, resp.message = self.cell_command(
            req.command, req.source or "operator"
        )
        with self._cond:
            resp.state_current = self._last_msg.state_current if self._last_msg else 0
        resp.state_requested = (
            int(TARGET.get(Cmd(req.command), 0)) if resp.accepted else resp.state_current
        )
        return resp

    def _srv_trigger(
        self, cmd: Cmd, req: Trigger.Request, resp: Trigger.Response
    ) -> Trigger.Response:
        resp.success, _, resp.message = self.cell_command(cmd, "operator")
        return resp

    def _srv_set_mode(self, req: SetMode.Request, resp: SetMode.Response) -> SetMode.Response:
        resp.accepted, resp.result, resp.message, resp.mode_current = self.cell_set_mode(
            req.mode, req.mode_name, req.source or "operator"
        )
        return resp

    def _srv_episodes(
        self, req: QueryEpisodes.Request, resp: QueryEpisodes.Response
    ) -> QueryEpisodes.Response:
        since, until, unit, bucket = (
            line_msgs.ns_of(req.since),
            line_msgs.ns_of(req.until),
            req.unit[:200],
            req.bucket[:40],
        )
        with self._cond:
            why = self.line.episode_filter_problem(since, until, unit, bucket)
            if why:
                resp.accepted, resp.result, resp.message = False, Result.INVALID_ARGUMENT, why
                return resp
            found, total = self.line.query_episodes(
                since, until, unit, req.reason[:200], bucket, req.open_only, req.limit
            )
        resp.accepted, resp.result, resp.total = True, Result.ACCEPTED, total
        resp.message = f"{len(found)} of {total} episodes"
        resp.episodes = [line_msgs.episode_msg(v, self.cell.cell) for v in found]
        return resp

    def _srv_losses(
        self, req: QueryLosses.Request, resp: QueryLosses.Response
    ) -> QueryLosses.Response:
        with self._cond:
            now = self._wall()
            views, why = self.line.query_losses(
                req.window[:100],
                line_msgs.ns_of(req.since),
                line_msgs.ns_of(req.until),
                req.step,
                req.count,
            )
            designs = self._designs()
        resp.accepted = not why
        resp.result = Result.ACCEPTED if not why else Result.INVALID_ARGUMENT
        resp.message = why or f"{len(views)} window(s)"
        resp.windows = [line_msgs.losses_msg(v, self.cell.cell, now, designs) for v in views]
        return resp

    def _srv_reset_losses(self, req: Trigger.Request, resp: Trigger.Response) -> Trigger.Response:
        with self._cond:
            self.line.reset_losses()
            self._flush()
        resp.success, resp.message = (
            True,
            "the since-reset window of the line's losses begins now" + self._durability_note(),
        )
        self.get_logger().info("line losses: since-reset window reset")
        return resp

    # ==============================================================================================
    def close(self) -> None:
        """End running sequences and close the line's store; the timer does nothing from now on
        (idempotent; destroy_node calls it too). The timer itself goes with the node: destroying it
        here, while an executor thread may still run it, made that thread fail ("cannot use
        Destroyable")."""
        with self._cond:
            if self._closed:
                return
            self._closed = True
            self.line.runs.cancel_all("shutdown")
            self._cond.notify_all()
            self.line.close()
        if self.context.ok():
            reason = run.shutdown_reason() or "node closed"
            self.get_logger().info(f"coordinator of {self.cell.cell} shut down ({reason})")

    def destroy_node(self) -> None:
        self.close()
        for proxy in self._proxies.values():
            proxy.destroy()
        super().destroy_node()


def main(argv: Sequence[str] | None = None) -> int:
    import rclpy

    args = run.init(argv)
    if not args or args[0] in ("-h", "--help"):
        print(__doc__)
        rclpy.try_shutdown()
        return 0 if args else 2
    try:
        cell = load_cell(args[0])
    except ConfigError as exc:
        print(exc.prefixed("coordinator"), file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    except Exception as exc:  # one readable message, exit 2
        print(f"coordinator: {exc}", file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    if not cell.coordinator.enabled:
        print(f"coordinator: disabled in {args[0]} (coordinator.enabled: false)", file=sys.stderr)
        rclpy.try_shutdown()
        return 0
    try:
        node = CoordinatorNode(cell)
    except StoreError as exc:
        print(f"coordinator: {exc}", file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    on_shutdown: Callable[[], None] = node.close
    return run.spin([node], threads=THREADS, on_shutdown=on_shutdown)


if __name__ == "__main__":
    sys.exit(main())
