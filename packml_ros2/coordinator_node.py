"""The cell coordinator: the ISA-88 "procedure" level above the units of a cell (PACKML.md section 4).

Node ``/<cell>/coordinator``. Services: ``command`` (packml_interfaces/Command), ``set_mode``
(SetMode) and the Trigger shortcuts ``reset`` ... ``complete``, all fanned out to the units through
their remote path (source ``remote:coordinator``: a unit accepts it only while its parameter
``remote_commands_enabled`` is true). Topic: ``status`` (CellStatus, latched, DDS liveliness
with lease ``unit_lease`` like the units' status), published on every change.

Sequencing: start-like commands (RESET, START, UNHOLD, UNSUSPEND, CLEAR) go to the units in
``start_order``, stop-like ones (STOP, HOLD, SUSPEND, COMPLETE) in ``stop_order``; units that are
not listed follow in configuration order. Each step waits until the unit reached the state its
answer names as ``state_requested`` before the next unit is commanded. A unit already in (or on
its way to) the command's target state is skipped. All or nothing: before any unit is commanded,
every unit is checked (online, remote commands enabled, the command valid in its state by its own
``Status.commands_valid``); one that cannot take it refuses the command for the cell, and the answer
names it and why. STOP is the exception the standard makes: it goes to every unit that can stop
(one that cannot is skipped, one that refuses is reported, the others stop all the same). A unit
that refuses anyway, a step longer than ``step_timeout`` or a lost unit ends the sequence; the
answer names the unit and quotes its reason. ``set_mode`` is all or nothing too: every unit is
checked by its mode rules (core.rules) first; a unit that refuses anyway has the units changed
before it changed back; a refused change answers with the mode the cell still has.
ABORT goes to every unit at once (safety) and, like STOP, cancels a running sequence; any other
command is refused while a sequence runs. The service handlers block while a sequence runs: spin
the node with a MultiThreadedExecutor (``main`` does).

Cell state (``CellStatus.state_current``): the online units' common state, otherwise the most
severe by :data:`SEVERITY`: Aborting > Aborted > Stopping > Clearing > Stopped > Holding > Held >
Suspending > Suspended > Unholding > Unsuspending > Resetting > Starting > Completing > Idle >
Complete > Execute (acting before wait states in each group: the cell is still moving; the cell is
in Execute only when every online unit is).

Lost units: a unit is online (once its latched status arrived) while anything of it arrives
(status, transitions, admin, alarms, or its ``packml: <unit>`` entry with hardware_id
``<cell>/<unit>`` on ``/diagnostics``, which every unit publishes once per second).
Nothing for ``unit_lease`` seconds: it is lost (``lost_units``, health ``offline``, a warning in
the log), and back online with its next status (the status held from before a network partition
may be stale: when anything else of a lost unit arrives first, the coordinator subscribes to its
status and transitions again, which delivers the latest ones at once). A unit never heard of since the coordinator
started is reported lost after ``unit_lease`` as well. ``unit_lease`` should exceed the 1 s
diagnostics period: detection takes between ``unit_lease - 1`` and ``unit_lease`` (+0.1 s) seconds.

Interlocks (``propagate_interlocks``): while a rule's unit reports ``blocked`` / ``starved``, the
coordinator holds an interlock (``set_interlock``, source ``coordinator``, reason ``"<unit>
blocked"``) on each unit of the rule's ``suspend`` list; the unit suspends itself and unsuspends
when it is cleared. One interlock per target unit combines every rule that holds it (the unit
keeps one interlock per source). Requests go out on changes only, and again to a unit that comes
back online (and once at first contact: it clears an interlock a previous coordinator left). A
unit's condition is what its active EMs report (``Status.equipment_modules[].blocked/starved``):
its EquipmentInterlock flag also rises with external interlocks, the coordinator's own among them,
and propagating those would cascade and could lock two units into each other. A lost unit keeps
its last known condition.

Run: ``coordinator <cell.yaml>`` or ``python -m packml_ros2.coordinator_node <cell.yaml>``.
"""

from __future__ import annotations

import itertools
import sys
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field
from functools import partial
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from packml_interfaces.msg import CellStatus, Result, Status, TransitionEvent, UnitSummary
from packml_interfaces.srv import Command, SetMode
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from std_srvs.srv import Trigger

from . import qos, responses, run
from .client import Unavailable, UnitProxy
from .core import WAIT, CellConfig, Cmd, ConfigError, State, load_cell, state_name, unit_config
from .core.numbers import names_of
from .core.rules import rules_of

#: Source of the unit commands the coordinator sends (the units' remote path).
SOURCE = "remote:coordinator"
#: Source of the interlocks it sets (``<unit>/set_interlock``).
INTERLOCK_SOURCE = "coordinator"
START_LIKE = frozenset({Cmd.RESET, Cmd.START, Cmd.UNHOLD, Cmd.UNSUSPEND, Cmd.CLEAR})
STOP_LIKE = frozenset({Cmd.STOP, Cmd.HOLD, Cmd.SUSPEND, Cmd.COMPLETE})
#: The wait state each command leads to (the rule book's, core.rules.Rules.command_target); a
#: unit whose StateRequested is already this is skipped.
TARGET: dict[Cmd, State] = {
    c: t for c in Cmd if c and (t := rules_of(unit_config()).command_target(c)) is not None
}
#: Aggregate cell state when the units disagree: the first of these that any online unit is in.
SEVERITY: tuple[State, ...] = (
    State.ABORTING, State.ABORTED,
    State.STOPPING, State.CLEARING, State.STOPPED,
    State.HOLDING, State.HELD,
    State.SUSPENDING, State.SUSPENDED,
    State.UNHOLDING, State.UNSUSPENDING, State.RESETTING, State.STARTING, State.COMPLETING,
    State.IDLE, State.COMPLETE, State.EXECUTE,
)  # fmt: skip
_RANK = {s: i for i, s in enumerate(SEVERITY)}
TICK = 0.1  # s: lease checks and interlock retries
INTERLOCK_RETRY = 0.5  # s between attempts when set_interlock failed
THREADS = 8  # executor threads of main(): sequences block one each, callbacks need the rest


def _ns(stamp: Any) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def aggregate_state(states: Sequence[int]) -> int:
    """The common state, or the most severe one (:data:`SEVERITY`); 0 for no state."""
    if not states:
        return int(State.UNDEFINED)
    if len(set(states)) == 1:
        return int(states[0])
    return int(min(states, key=lambda s: _RANK.get(s, len(SEVERITY))))


@dataclass
class _Unit:
    """What the coordinator knows about one unit."""

    name: str
    proxy: UnitProxy
    last_seen: float
    online: bool = False
    lost: bool = False  # reported lost (went silent, or never seen within unit_lease of start)
    status: Status | None = None
    # (sequence, to_state, command, source, trigger) of recent transitions
    transitions: list[tuple[int, int, int, str, int]] = field(default_factory=list)
    interlock_sent: bool | None = None  # what the unit holds from us (None: unknown)
    interlock_reason: str = ""
    interlock_pending: bool = False
    interlock_retry_at: float = 0.0
    interlock_error: str = ""
    lost_reason: str = ""
    resubscribed: bool = False  # since it was lost
    resubscribe_due: bool = False

    def sequence(self) -> int:
        seqs = [self.status.sequence] if self.status else []
        if self.transitions:
            seqs.append(self.transitions[-1][0])
        return max(seqs, default=0)


class _Failed(Exception):
    """A sequence step failed: result code and message."""

    def __init__(self, result: int, message: str) -> None:
        super().__init__(message)
        self.result = result
        self.message = message


class CoordinatorNode(Node):
    """The coordinator of ``cell``: node ``coordinator`` in ``/<cell>``."""

    def __init__(self, cell: CellConfig, **node_kwargs: Any) -> None:
        namespace = node_kwargs.pop("namespace", f"/{cell.cell}")
        super().__init__("coordinator", namespace=namespace, **node_kwargs)
        self.cell = cell
        self.config = cell.coordinator
        names = list(cell.units)
        self.start_order = [*self.config.start_order, *(n for n in names if n not in self.config.start_order)]  # fmt: skip
        self.stop_order = [*self.config.stop_order, *(n for n in names if n not in self.config.stop_order)]  # fmt: skip
        self._cond = threading.Condition(threading.RLock())
        self._group = ReentrantCallbackGroup()
        self._started = time.monotonic()
        self._units: dict[str, _Unit] = {
            name: _Unit(name, UnitProxy(self, f"/{cell.cell}/{name}", self._on_unit), self._started)
            for name in names
        }
        self._hardware_ids = {f"{cell.cell}/{name}": name for name in names}
        self._seq_lock = threading.Lock()
        self._run_ids = itertools.count(1)
        self._runs: dict[int, str] = {}  # running sequences: id -> what they wait for
        self._cancelled: dict[int, str] = {}  # id -> by which command
        self._aborts: set[int] = set()  # ids of ABORT runs
        self._stops: set[int] = set()  # ids of STOP runs (another STOP joins them)
        self._last_result = ""
        self._last_msg: CellStatus | None = None
        self._closed = False

        # with the units' liveliness lease: faces see a coordinator that is gone within it
        # (packml_ros2.presence); subscribers with the default QoS are unaffected
        self.pub_status = self.create_publisher(
            CellStatus, "~/status", qos.with_lease(qos.CELL_STATUS, self.config.unit_lease)
        )
        self.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics,
                                 qos.DIAGNOSTICS, callback_group=self._group)  # fmt: skip
        serve = partial(responses.create_service, self, callback_group=self._group)
        serve(Command, "~/command", self._srv_command)
        serve(SetMode, "~/set_mode", self._srv_set_mode)
        for cmd in Cmd:
            if cmd:
                serve(Trigger, f"~/{cmd.name.lower()}", partial(self._srv_trigger, cmd))
        self._timer = self.create_timer(TICK, self._on_tick, callback_group=self._group)
        if self.config.unit_lease <= 1.0:
            self.get_logger().warning(
                f"unit_lease {self.config.unit_lease:g} s is not longer than the units' 1 s "
                "diagnostics period: idle units will flap between online and lost"
            )
        with self._cond:
            self._publish()
        self.get_logger().info(
            f"coordinator of {cell.cell} up: units {', '.join(names)}; start order "
            f"{' > '.join(self.start_order)}, stop order {' > '.join(self.stop_order)}; "
            f"unit lease {self.config.unit_lease:g} s, step timeout {self.config.step_timeout:g} s"
        )

    # ================================================================================================
    # Units: what arrives, liveliness
    # ================================================================================================
    def _on_unit(self, path: str, topic: str, msg: Any) -> None:
        name = path.rsplit("/", 1)[-1]
        with self._cond:
            unit = self._units.get(name)
            if unit is None or self._closed:
                return
            fresh = topic == "status"
            if fresh and unit.status is not None and _ns(msg.stamp) < _ns(unit.status.stamp):
                fresh = False  # older than the one held (a resubscription's race): ignored
            elif fresh:
                if unit.status is not None and msg.sequence < unit.status.sequence:
                    # restarted without its admin data: sequence numbers start again
                    unit.transitions = [t for t in unit.transitions if t[0] <= msg.sequence]
                unit.status = msg
            self._seen(unit, fresh)
            if topic == "transitions":
                assert isinstance(msg, TransitionEvent)
                entry = (msg.sequence, msg.to_state, msg.command, msg.source, msg.trigger)
                if unit.transitions and msg.sequence <= unit.transitions[-1][0]:
                    if entry in unit.transitions:  # the latched history, delivered again
                        return
                    unit.transitions = [t for t in unit.transitions if t[0] < msg.sequence]
                unit.transitions.append(entry)
                del unit.transitions[:-200]
            self._cond.notify_all()
            self._reconcile_interlocks()
            self._publish()

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        with self._cond:
            if self._closed:
                return
            changed = False
            for entry in msg.status:
                name = self._hardware_ids.get(entry.hardware_id)
                if name is not None and entry.name == f"packml: {name}":
                    unit = self._units[name]
                    was_online = unit.online
                    if entry.level == DiagnosticStatus.STALE:  # a PLC bridge whose PLC is gone
                        if unit.online or not unit.lost:
                            self._lose(unit, entry.message)
                            changed = True
                        continue
                    self._seen(unit, fresh=False)
                    changed |= unit.online != was_online
            if changed:
                self._cond.notify_all()
                self._reconcile_interlocks()
                self._publish()

    def _seen(self, unit: _Unit, fresh: bool) -> None:
        """Something of the unit arrived: it is alive. It is online (again) with a status that
        arrived now (``fresh``): after a partition, the status it had before may be stale."""
        unit.last_seen = time.monotonic()
        if unit.online:
            return
        if not fresh:
            if unit.lost and not unit.resubscribed:
                # Back after a partition: its latest status would come by reliable repair at the
                # writer's next heartbeat; a new subscription gets it at once (see _on_tick).
                unit.resubscribed = unit.resubscribe_due = True
            return
        unit.online, unit.resubscribed = True, False
        if unit.lost:
            self.get_logger().info(f"unit {unit.name} online again")
        else:
            self.get_logger().info(f"unit {unit.name} online")
        unit.lost, unit.lost_reason = False, ""

    def _lose(self, unit: _Unit, why: str) -> None:
        """``unit`` is gone (lock held): no sign of life within the lease, or its bridge says its
        PLC is not reachable; the other units get ``lost_unit_reaction``."""
        was_online = unit.online
        unit.online, unit.lost, unit.lost_reason = False, True, why
        unit.interlock_sent = None  # unknown until it is back: send again
        last = unit.status.state_current_name if unit.status else "no status"
        self.get_logger().warning(f"unit {unit.name} lost: {why} (last seen in {last})")
        self._cond.notify_all()
        reaction = self.config.lost_unit_reaction
        if was_online and reaction:
            for other in self._units.values():
                if (
                    other is not unit
                    and other.online
                    and other.proxy.client("command").service_is_ready()
                ):
                    future = other.proxy.call("command", command=reaction, source=SOURCE)
                    future.add_done_callback(
                        partial(self._reacted, other.name, unit.name, reaction)
                    )

    def _reacted(self, name: str, lost: str, reaction: int, future: Future[Any]) -> None:
        exc = future.exception()
        answer = exc if exc is not None else future.result().message
        self.get_logger().info(f"{Cmd(reaction).name} to {name} because {lost} was lost: {answer}")

    def _on_tick(self) -> None:
        now = time.monotonic()
        lease = self.config.unit_lease
        with self._cond:
            if self._closed:
                return
            again = [u for u in self._units.values() if u.resubscribe_due]
            for unit in again:
                unit.resubscribe_due = False
        for unit in again:  # outside the lock: creating subscriptions takes the node's locks
            unit.proxy.resubscribe("status", "transitions")
        with self._cond:
            for unit in self._units.values():
                if unit.online and now - unit.last_seen > lease:
                    self._lose(unit, f"no status or diagnostics for {lease:g} s")
                elif not unit.online and not unit.lost and now - self._started > lease:
                    unit.lost = True
                    self.get_logger().warning(
                        f"unit {unit.name} not seen within {lease:g} s of the coordinator's start"
                    )
            self._reconcile_interlocks()
            self._publish()

    # ================================================================================================
    # Interlocks
    # ================================================================================================
    @staticmethod
    def _condition(unit: _Unit, condition: str) -> bool:
        """Whether the unit itself is blocked / starved: one of its active EMs says so. Its status
        flag (EquipmentInterlock) also rises with external interlocks, the coordinator's own
        among them; propagating those would cascade and could lock two units into each other."""
        status = unit.status
        return status is not None and any(
            getattr(em, condition) for em in status.equipment_modules if em.active
        )

    def _desired_interlocks(self) -> dict[str, list[str]]:
        desired: dict[str, list[str]] = {}
        for rule in self.config.interlocks:
            source = self._units.get(rule.unit)
            if source is not None and self._condition(source, rule.condition):
                for target in rule.suspend:
                    reasons = desired.setdefault(target, [])
                    if f"{rule.unit} {rule.condition}" not in reasons:
                        reasons.append(f"{rule.unit} {rule.condition}")
        return desired

    def _reconcile_interlocks(self) -> None:
        """Send what changed (called with the lock held)."""
        if not self.config.propagate_interlocks or self._closed:
            return
        desired = self._desired_interlocks()
        now = time.monotonic()
        for unit in self._units.values():
            reasons = desired.get(unit.name, [])
            want, reason = bool(reasons), "; ".join(reasons)
            if not unit.online or unit.interlock_pending or now < unit.interlock_retry_at:
                continue
            if unit.interlock_sent is want and (not want or reason == unit.interlock_reason):
                continue
            if not unit.proxy.client("set_interlock").service_is_ready():
                continue  # not discovered yet (or gone): the next tick tries again
            unit.interlock_pending = True
            future = unit.proxy.call(
                "set_interlock",
                active=want,
                reason=reason if want else (unit.interlock_reason or "cleared"),
                source=INTERLOCK_SOURCE,
            )
            future.add_done_callback(partial(self._interlock_done, unit, want, reason))

    def _interlock_done(self, unit: _Unit, want: bool, reason: str, future: Future[Any]) -> None:
        with self._cond:
            unit.interlock_pending = False
            what = f"interlock on {unit.name} ({reason})" if want else f"clearing the interlock on {unit.name}"  # fmt: skip
            exc = future.exception()
            answer = None if exc is not None else future.result()
            # (a clear of what the unit does not hold from us: nothing to do is done)
            done = answer is not None and (
                answer.accepted or (not want and answer.result == Result.NOTHING_TO_DO)
            )
            if not done:
                why = str(exc) if answer is None else answer.message
                unit.interlock_retry_at = time.monotonic() + INTERLOCK_RETRY
                if why != unit.interlock_error:  # once per distinct problem, not every retry
                    unit.interlock_error = why
                    self.get_logger().warning(f"{what} failed: {why}; retrying")
            else:
                previous = unit.interlock_sent
                unit.interlock_error = ""
                unit.interlock_sent, unit.interlock_reason = want, reason if want else ""
                if want or previous:
                    self.get_logger().info(
                        f"interlock set on {unit.name}: {reason}" if want
                        else f"interlock cleared on {unit.name}"
                    )  # fmt: skip
            self._reconcile_interlocks()
            self._publish()

    # ================================================================================================
    # Cell status
    # ================================================================================================
    def _summary(self, unit: _Unit) -> UnitSummary:
        s = unit.status
        out = UnitSummary(name=unit.name, online=unit.online)
        if s is not None:
            ems = s.equipment_modules
            out.state_current = s.state_current
            out.state_current_name = s.state_current_name
            out.unit_mode_current = s.unit_mode_current
            out.unit_mode_current_name = s.unit_mode_current_name
            out.sequence = s.sequence
            out.remote_commands_enabled = s.remote_commands_enabled
            out.em_total = len(ems)
            out.em_online = sum(1 for e in ems if e.online)
            out.active_alarms = s.active_alarms
            out.alarm_banner = s.alarm_banner
            out.blocked = s.equipment_interlock.blocked
            out.starved = s.equipment_interlock.starved
            out.interlock_suspended = bool(unit.interlock_sent) and s.state_current in (
                State.SUSPENDING,
                State.SUSPENDED,
            )
        else:
            out.state_current_name = state_name(State.UNDEFINED)
        if not unit.online:
            out.health = "offline"
        elif s is not None and any(e.active and not e.online for e in s.equipment_modules):
            out.health = "em lost"
        elif s is not None and s.active_alarms:
            out.health = "alarm"
        else:
            out.health = "ok"
        return out

    def _publish(self) -> None:
        """Publish the cell status if anything but the stamp changed (lock held)."""
        units = list(self._units.values())
        present = [u for u in units if u.online and u.status is not None]
        state = aggregate_state([u.status.state_current for u in present if u.status])
        modes = {u.status.unit_mode_current for u in present if u.status}
        lost = [u.name for u in units if u.lost]
        why = [f"{u.name} ({u.lost_reason})" if u.lost_reason else u.name for u in units if u.lost]
        detail = []
        if not present:
            detail.append("no unit online")
        elif len({u.status.state_current for u in present if u.status}) > 1:
            detail.append(
                "mixed: " + ", ".join(f"{u.name} {u.status.state_current_name}" for u in present if u.status)
            )  # fmt: skip
        if lost:
            detail.append(f"lost: {', '.join(why)}")
        held = [f"{u.name} ({u.interlock_reason})" for u in units if u.interlock_sent]
        if held:
            detail.append(f"interlock on {', '.join(held)}")
        if self._last_result:
            detail.append(f"last: {self._last_result}")
        msg = CellStatus(
            cell=self.cell.cell,
            units=[self._summary(u) for u in units],
            state_current=state,
            state_current_name=state_name(state),
            unit_mode_current=modes.pop() if len(modes) == 1 else 0,
            all_online=all(u.online for u in units),
            busy=bool(self._runs),
            sequence_step=next(reversed(self._runs.values()), ""),
            lost_units=lost,
            detail="; ".join(detail),
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

    # ================================================================================================
    # Services
    # ================================================================================================
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

    def _srv_trigger(self, cmd: Cmd, req: Trigger.Request, resp: Trigger.Response) -> Trigger.Response:  # fmt: skip
        resp.success, _, resp.message = self.cell_command(cmd, "operator")
        return resp

    def _srv_set_mode(self, req: SetMode.Request, resp: SetMode.Response) -> SetMode.Response:
        resp.accepted, resp.result, resp.message, resp.mode_current = self.cell_set_mode(
            req.mode, req.mode_name, req.source or "operator"
        )
        return resp

    def _not_blocking_executor(self) -> str:
        """Why the handlers may not block here ('' = they may)."""
        if isinstance(self.executor, MultiThreadedExecutor):
            return ""
        return (
            "the coordinator must be spun by a MultiThreadedExecutor (its services wait for the "
            "units while their status keeps arriving)"
        )

    # -- cell commands --------------------------------------------------------------------------------------
    def cell_command(self, cmd: int, caller: str = "operator") -> tuple[bool, int, str]:
        """Run cell command ``cmd`` (blocks until the sequence ended): (accepted, result, message)."""
        if not 1 <= cmd <= 10:
            return False, Result.UNKNOWN_COMMAND, f"command {cmd} is not a PackML command (1..10)"
        problem = self._not_blocking_executor()
        if problem:
            return False, Result.UNIT_UNAVAILABLE, problem
        command = Cmd(cmd)
        started = time.monotonic()
        if command is Cmd.ABORT:
            ok, result, message = self._abort()
        else:
            ok, result, message = self._sequence(command)
        text = f"{command.name} from {caller}: {message}"
        if ok:  # rclpy ties a severity to each call site: one call per level
            self.get_logger().info(text)
        else:
            self.get_logger().warning(text)
        with self._cond:
            self._last_result = f"{command.name} {'done' if ok else 'failed'} ({time.monotonic() - started:.1f} s)"  # fmt: skip
            self._publish()
        return ok, result, message

    def _register(self, what: str) -> int:
        with self._cond:
            run_id = next(self._run_ids)
            self._runs[run_id] = what
            self._publish()
            return run_id

    def _step_text(self, run_id: int, text: str) -> None:
        with self._cond:
            if run_id in self._runs:
                self._runs[run_id] = text
                self._publish()

    def _unregister(self, run_id: int) -> None:
        with self._cond:
            self._runs.pop(run_id, None)
            self._cancelled.pop(run_id, None)
            self._aborts.discard(run_id)
            self._stops.discard(run_id)
            self._publish()

    def _cancel_all(self, by: str) -> None:
        """End running sequences and mode fan-outs (an ABORT in progress is never cancelled, a
        STOP not by another STOP: that one joins it)."""
        with self._cond:
            spared = self._aborts | (self._stops if by == "STOP" else set())  # (joined instead)
            for run_id in self._runs:
                if run_id not in spared:
                    self._cancelled.setdefault(run_id, by)
            self._cond.notify_all()

    def _check_cancelled(self, run_id: int, where: str) -> None:
        by = self._cancelled.get(run_id)
        if by is not None:
            raise _Failed(Result.SUPERSEDED, f"cancelled at {where} by {by}")

    def _sequence(self, cmd: Cmd) -> tuple[bool, int, str]:
        name = cmd.name
        if cmd is Cmd.STOP:  # cancels what runs, and whatever sneaks in before it got the lock
            give_up = time.monotonic() + self.config.step_timeout + 5.0
            acquired = False
            while not acquired and time.monotonic() < give_up:
                with self._cond:  # a STOP runs already: this one joins it (no thread waits)
                    running = [self._runs[r] for r in self._stops if r in self._runs]
                if running:
                    return True, Result.ACCEPTED, f"STOP joined the STOP in progress ({running[0]})"
                self._cancel_all("STOP")
                acquired = self._seq_lock.acquire(timeout=0.1)
        else:
            acquired = self._seq_lock.acquire(blocking=False)
        if not acquired:
            with self._cond:
                running = next(reversed(self._runs.values()), "a sequence")
            return False, Result.COMMAND_NOT_ALLOWED, f"{name} refused: busy ({running})"
        order = self.start_order if cmd in START_LIKE else self.stop_order
        if cmd is not Cmd.STOP:  # all or nothing (STOP goes to every unit that can stop)
            with self._cond:
                refusals = self._refusals(cmd, order)
            if refusals:
                self._seq_lock.release()
                listed = "; ".join(text for _, text in refusals)
                return False, refusals[0][0], f"{name} refused, no unit commanded: {listed}"
        run_id = self._register(f"{name}: starting")
        if cmd is Cmd.STOP:
            with self._cond:
                self._stops.add(run_id)
        done: list[str] = []
        skipped: list[str] = []
        failed: list[tuple[int, str]] = []
        try:
            for index, unit_name in enumerate(order, 1):
                where = f"{unit_name} (step {index}/{len(order)})"
                try:
                    outcome, text = self._step(
                        run_id, cmd, self._units[unit_name], index, len(order)
                    )
                except _Failed as failure:
                    if cmd is Cmd.STOP and failure.result != Result.SUPERSEDED:
                        failed.append((failure.result, f"{where}: {failure.message}"))
                        continue  # the others stop all the same
                    parts = [f"{name} stopped at {where}: {failure.message}"]
                    if done:
                        parts.append(f"done before: {', '.join(done)}")
                    if skipped:
                        parts.append(f"skipped: {', '.join(skipped)}")
                    rest = order[index:]
                    if rest:
                        parts.append(f"not commanded: {', '.join(rest)}")
                    return False, failure.result, "; ".join(parts)
                (done if outcome == "done" else skipped).append(text)
            parts = [f"{name} done in order {' > '.join(order)}"]
            if done:
                parts.append(", ".join(done))
            if skipped:
                parts.append(f"skipped: {', '.join(skipped)}")
            if failed:
                parts[0] = f"{name} not done on every unit (order {' > '.join(order)})"
                parts.append(f"failed: {'; '.join(text for _, text in failed)}")
                return False, failed[0][0], "; ".join(parts)
            return True, Result.ACCEPTED, "; ".join(parts)
        finally:
            self._unregister(run_id)
            self._seq_lock.release()

    def _refusals(self, cmd: Cmd, order: list[str]) -> list[tuple[int, str]]:
        """(Lock held.) Why units cannot take ``cmd`` now, from their last status: offline, remote
        commands disabled, the command not valid in their state (the unit's own judgement,
        ``Status.commands_valid``). Units already at or on their way to the target are fine."""
        out: list[tuple[int, str]] = []
        target = TARGET[cmd]
        for name in order:
            unit = self._units[name]
            status = unit.status
            if not unit.online or status is None:
                since = time.monotonic() - unit.last_seen
                out.append((Result.UNIT_UNAVAILABLE, f"{name} is offline (nothing from it for {since:.1f} s)"))  # fmt: skip
            elif status.state_requested == target:
                continue
            elif not status.remote_commands_enabled:
                out.append((Result.REMOTE_DISABLED, f"{name} does not take remote commands (remote_commands_enabled is false)"))  # fmt: skip
            elif int(cmd) not in status.commands_valid:
                valid = names_of(status.commands_valid) or "none"
                out.append((Result.COMMAND_NOT_ALLOWED, f"{name} cannot take {cmd.name} in {status.state_current_name} (valid now: {valid})"))  # fmt: skip
        return out

    def _step(self, run_id: int, cmd: Cmd, unit: _Unit, index: int, total: int) -> tuple[str, str]:
        """Command one unit and wait for it: ('done' | 'skipped', text), or raise _Failed."""
        started = time.monotonic()
        deadline = started + self.config.step_timeout
        target = TARGET[cmd]
        step = f"{cmd.name} {index}/{total}: {unit.name}"
        with self._cond:
            self._check_cancelled(run_id, unit.name)
            self._require_online(unit)
            status = unit.status
            assert status is not None  # online units have sent something; status is latched
            seq0 = unit.sequence()
            if status.state_requested == target:
                if status.state_current == target:
                    return "skipped", f"{unit.name} (already {state_name(target)})"
                self._runs[run_id] = f"{step} on its way to {state_name(target)}"
                self._publish()
                self._wait_reached(run_id, unit, None, seq0, target, deadline)
                return "done", f"{unit.name} -> {state_name(target)} (was on its way)"
            if cmd is Cmd.STOP and int(cmd) not in status.commands_valid:
                return "skipped", f"{unit.name} (cannot stop in {status.state_current_name})"
        self._step_text(run_id, f"{step}: sending {cmd.name}")
        resp = self._call(run_id, unit, "command", deadline, command=int(cmd), source=SOURCE)
        if not resp.accepted:
            raise _Failed(resp.result, f"{unit.name} refused {cmd.name}: {resp.message}")
        requested = resp.state_requested
        if resp.state_current != requested:
            self._step_text(run_id, f"{step}: waiting for {state_name(requested)}")
            with self._cond:
                self._wait_reached(run_id, unit, cmd, seq0, requested, deadline)
        return (
            "done",
            f"{unit.name} -> {state_name(requested)} ({time.monotonic() - started:.2f} s)",
        )

    def _require_online(self, unit: _Unit) -> None:
        if not unit.online or unit.status is None:
            since = time.monotonic() - unit.last_seen
            raise _Failed(
                Result.UNIT_UNAVAILABLE,
                f"{unit.name} is offline (no status or diagnostics for {since:.1f} s)",
            )

    def _wait_reached(self, run_id: int, unit: _Unit, cmd: Cmd | None, seq0: int, target: int,
                      deadline: float) -> None:  # fmt: skip
        """Wait (lock held) until ``unit`` reached ``target`` after sequence ``seq0``."""
        while True:
            progress = self._progress(unit, cmd, seq0, target)
            if progress == "reached":
                return
            if progress:
                raise _Failed(
                    Result.COMMAND_NOT_ALLOWED,
                    f"{unit.name} went to {progress} instead of {state_name(target)}",
                )
            self._check_cancelled(run_id, unit.name)
            if not unit.online:
                raise _Failed(
                    Result.UNIT_UNAVAILABLE,
                    f"{unit.name} was lost while going to {state_name(target)}",
                )
            now = time.monotonic()
            if now >= deadline:
                current = unit.status.state_current_name if unit.status else "no status"
                raise _Failed(
                    Result.UNIT_UNAVAILABLE,
                    f"{unit.name} did not reach {state_name(target)} within "
                    f"{self.config.step_timeout:g} s (step_timeout; now {current})",
                )
            self._cond.wait(min(deadline - now, 0.5))

    @staticmethod
    def _progress(unit: _Unit, cmd: Cmd | None, seq0: int, target: int) -> str:
        """'reached', the name of the wait state the unit settled in instead, or ''."""
        later = [t for t in unit.transitions if t[0] > seq0]
        if cmd is not None:
            # From the command's own transition on (older ones may still be in flight).
            mine = next((t[0] for t in later if t[2] == cmd and t[3] == SOURCE), None)
            later = [t for t in later if mine is not None and t[0] >= mine]
        for _, to_state, _, _, trigger in later:
            if to_state == target:
                return "reached"
            if to_state in WAIT and trigger != TransitionEvent.TRIGGER_MODE:
                return state_name(to_state)
        status = unit.status
        if status is not None and status.state_current == target and status.sequence > seq0:
            return "reached"
        if cmd is None and status is not None and status.state_current == target:
            return "reached"
        return ""

    def _call(self, run_id: int, unit: _Unit, service: str, deadline: float, **fields: Any) -> Any:
        """Call a unit service from a handler thread: waits for it to appear and answer, gives up
        at ``deadline``, when the unit is lost or the sequence is cancelled."""
        client = unit.proxy.client(service)
        future: Future[Any] | None = None
        while True:
            with self._cond:
                self._check_cancelled(run_id, unit.name)
                self._require_online(unit)
            if future is None and client.service_is_ready():
                future = unit.proxy.call(service, **fields)
            if future is not None:
                try:
                    return future.result(timeout=0.05)
                except TimeoutError:
                    pass
                except Unavailable as exc:
                    raise _Failed(Result.UNIT_UNAVAILABLE, str(exc)) from None
            else:
                time.sleep(0.02)
            if time.monotonic() >= deadline:
                what = "did not answer" if future is not None else "is not available"
                raise _Failed(
                    Result.UNIT_UNAVAILABLE,
                    f"{unit.name}/{service} {what} within {self.config.step_timeout:g} s",
                )

    # -- abort: everyone at once ------------------------------------------------------------------------------
    def _abort(self) -> tuple[bool, int, str]:
        self._cancel_all("ABORT")
        run_id = self._register("ABORT: sending to every unit")
        with self._cond:
            self._aborts.add(run_id)
        started = time.monotonic()
        deadline = started + self.config.step_timeout
        target = TARGET[Cmd.ABORT]
        futures: dict[str, tuple[Future[Any], int]] = {}
        results: dict[str, str] = {}
        failed: list[tuple[int, str]] = []
        try:
            with self._cond:
                for unit in self._units.values():
                    status = unit.status
                    if status is not None and status.state_requested == target and unit.online:
                        results[unit.name] = f"{unit.name} already {status.state_current_name}"
                        continue
                    client = unit.proxy.client("command")
                    if not client.service_is_ready():  # lost units too: try whoever is there
                        results[unit.name] = f"{unit.name} unreachable"
                        failed.append((Result.UNIT_UNAVAILABLE, results[unit.name]))
                        continue
                    seq0 = unit.sequence()
                    futures[unit.name] = (
                        unit.proxy.call("command", command=int(Cmd.ABORT), source=SOURCE),
                        seq0,
                    )
            self._step_text(run_id, f"ABORT: waiting for {', '.join(futures) or 'nobody'}")
            for name, (future, seq0) in futures.items():
                unit = self._units[name]
                try:
                    resp = future.result(timeout=max(0.0, deadline - time.monotonic()))
                except Exception as exc:  # TimeoutError, Unavailable
                    results[name] = f"{name} did not answer ({str(exc) or 'timeout'})"
                    failed.append((Result.UNIT_UNAVAILABLE, results[name]))
                    continue
                if not resp.accepted:
                    results[name] = f"{name} refused ABORT: {resp.message}"
                    failed.append((resp.result, results[name]))
                    continue
                try:
                    with self._cond:
                        if resp.state_current != resp.state_requested:
                            self._wait_reached(
                                run_id, unit, Cmd.ABORT, seq0, resp.state_requested, deadline
                            )
                    results[name] = f"{name} -> {state_name(resp.state_requested)}"
                except _Failed as failure:
                    results[name] = failure.message
                    failed.append((failure.result, failure.message))
        finally:
            self._unregister(run_id)
        listed = "; ".join(results[n] for n in self._units if n in results)
        if failed:
            return False, failed[0][0], f"ABORT sent to every unit at once, not all aborted: {listed}"  # fmt: skip
        return True, Result.ACCEPTED, f"ABORT sent to every unit at once: {listed}"

    # -- modes --------------------------------------------------------------------------------------------------
    def cell_set_mode(self, mode: int, mode_name: str = "", caller: str = "operator") -> tuple[bool, int, str, int]:  # fmt: skip
        """A mode change of every unit, all or nothing: every unit is checked first (online, remote
        commands enabled, no change in process, the mode configured, the change allowed in its
        state by its mode rules); then it goes to every unit (start order); a unit that refuses
        anyway has the others changed back. (accepted, result, message, mode): the new mode, or
        the mode the cell had (0: mixed) when refused."""
        wanted = mode_name or str(mode)
        problem = self._not_blocking_executor()
        if problem:
            return False, Result.UNIT_UNAVAILABLE, problem, 0
        with self._cond:
            before = {n: u.status.unit_mode_current for n, u in self._units.items() if u.status}
        old = next(iter(set(before.values()))) if len(set(before.values())) == 1 else 0
        if not self._seq_lock.acquire(blocking=False):
            with self._cond:
                running = next(reversed(self._runs.values()), "a sequence")
            return False, Result.COMMAND_NOT_ALLOWED, f"mode {wanted} refused: busy ({running})", old  # fmt: skip
        run_id = self._register(f"SET_MODE {wanted}")
        lines: list[str] = []
        try:
            with self._cond:
                refusals, number = self._mode_refusals(mode, mode_name)
            if refusals:
                message = f"mode {wanted} refused, no unit changed: " + "; ".join(t for _, t in refusals)  # fmt: skip
                self.get_logger().warning(f"from {caller}: {message}")
                return False, refusals[0][0], message, old
            changed: list[str] = []
            for unit_name in self.start_order:
                unit = self._units[unit_name]
                self._step_text(run_id, f"SET_MODE {wanted}: {unit_name}")
                deadline = time.monotonic() + self.config.step_timeout
                try:
                    resp = self._call(run_id, unit, "set_mode", deadline, mode=int(mode),
                                      mode_name=mode_name, source=SOURCE)  # fmt: skip
                    result, text = resp.result, resp.message
                except _Failed as failure:
                    resp, result, text = None, failure.result, failure.message
                if resp is not None and resp.accepted:
                    lines.append(f"{unit_name}: accepted ({text})")
                    if before.get(unit_name) != number:
                        changed.append(unit_name)
                    continue
                undone = self._change_back(run_id, changed, number, before)
                message = (f"mode {wanted} not set: {unit_name} refused: {text}; "
                           f"{'changed back: ' + undone if changed else 'no unit changed'}")  # fmt: skip
                self.get_logger().warning(f"from {caller}: {message}")
                return False, result, message, old
        finally:
            self._unregister(run_id)
            self._seq_lock.release()
        message = f"mode {wanted} set on every unit: " + "; ".join(lines)
        self.get_logger().info(f"from {caller}: {message}")
        return True, Result.ACCEPTED, message, number

    def _mode_refusals(self, mode: int, mode_name: str) -> tuple[list[tuple[int, str]], int]:
        """(Lock held.) Why units cannot change to the mode now, from their last status and their
        configuration's mode rules (core.rules); and the mode's number."""
        out: list[tuple[int, str]] = []
        number = mode
        for name, unit in self._units.items():
            config = self.cell.units[name]
            target = config.mode_by_name(mode_name) if mode_name else config.modes.get(mode)
            status = unit.status
            if target is None:
                out.append((Result.MODE_UNKNOWN, f"{name} has no mode {mode_name or mode}"))
                continue
            number = target.number
            if not unit.online or status is None:
                out.append((Result.UNIT_UNAVAILABLE, f"{name} is offline"))
            elif not status.remote_commands_enabled:
                out.append((Result.REMOTE_DISABLED, f"{name} does not take remote commands (remote_commands_enabled is false)"))  # fmt: skip
            elif status.unit_mode_change_in_process:
                out.append((Result.MODE_CHANGE_IN_PROCESS, f"{name} is changing its mode already"))
            elif status.unit_mode_current != target.number:
                why = rules_of(config).mode_change_refusal(
                    status.unit_mode_current, target.number, State(status.state_current)
                )
                if why is not None:
                    out.append((Result.MODE_CHANGE_NOT_ALLOWED,
                                f"{name} in {status.state_current_name}: {why}"))  # fmt: skip
        return out, number

    def _change_back(self, run_id: int, changed: list[str], number: int,
                     before: dict[str, int]) -> str:  # fmt: skip
        """Put the units ``changed`` to ``number`` back to their mode of ``before``, once their
        change is done (its EMs confirm it): what happened, per unit."""
        notes = []
        for name in changed:
            unit = self._units[name]
            deadline = time.monotonic() + self.config.step_timeout
            with self._cond:
                while unit.status is not None and (
                    unit.status.unit_mode_change_in_process or unit.status.unit_mode_current != number
                ) and time.monotonic() < deadline:  # fmt: skip
                    self._cond.wait(min(0.5, max(0.0, deadline - time.monotonic())))
            try:
                resp = self._call(run_id, unit, "set_mode", deadline, mode=before[name],
                                  mode_name="", source=SOURCE)  # fmt: skip
                notes.append(f"{name} ({'back' if resp.accepted else 'refused: ' + resp.message})")
            except _Failed as failure:
                notes.append(f"{name} (not back: {failure.message})")
        return ", ".join(notes)

    # ================================================================================================
    def close(self) -> None:
        """End running sequences; the timer does nothing from now on (idempotent; destroy_node
        calls it too). The timer itself goes with the node: destroying it here, while an executor
        thread may still run it, made that thread fail ("cannot use Destroyable")."""
        with self._cond:
            if self._closed:
                return
            self._closed = True
        self._cancel_all("shutdown")
        if self.context.ok():
            reason = run.shutdown_reason() or "node closed"
            self.get_logger().info(f"coordinator of {self.cell.cell} shut down ({reason})")

    def destroy_node(self) -> None:
        self.close()
        for unit in self._units.values():
            unit.proxy.destroy()
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
    node = CoordinatorNode(cell)
    on_shutdown: Callable[[], None] = node.close
    return run.spin([node], threads=THREADS, on_shutdown=on_shutdown)


if __name__ == "__main__":
    sys.exit(main())
