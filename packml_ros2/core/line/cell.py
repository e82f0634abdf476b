"""The cell as the coordinator sees it: its units (what arrived of each, whether it is online or
lost), the aggregate state, the interlock propagation, and what the coordinator publishes.

Pure: the clock is passed in (seconds, monotonic), messages are read through protocols, and what
the coordinator must do is returned as :class:`Effect` values the node carries out (log a line,
call a unit's service, subscribe again). The node holds one lock around every call.

Cell state: the online units' common state, otherwise the most severe by :data:`SEVERITY`:
Aborting > Aborted > Stopping > Clearing > Stopped > Holding > Held > Suspending > Suspended >
Unholding > Unsuspending > Resetting > Starting > Completing > Idle > Complete > Execute (acting
before wait states in each group: the cell is still moving; it is in Execute only when every
online unit is).

Lost units: a unit is online once its status arrived and while anything of it arrives (status,
transitions, admin, alarms, its ``packml: <unit>`` diagnostics entry). Nothing for
``unit_lease`` seconds, or a STALE diagnostics entry (a PLC bridge whose PLC is gone): it is lost,
and the other units get ``lost_unit_reaction``. Back online with its next status; anything else
arriving first asks for a new subscription to its status and transitions (the status held from
before a partition may be stale). A unit never heard of is reported lost after ``unit_lease``.

Interlocks: while a rule's unit reports ``blocked``/``starved`` through its active EMs, each unit
of the rule's ``suspend`` list holds an interlock from the coordinator (one per target, the
reasons of every rule that holds it joined). Requests go out on changes, again to a unit back
online, once at first contact, and after a failure every :data:`INTERLOCK_RETRY` seconds. The
unit's EquipmentInterlock flag is not used: it rises with external interlocks too, the
coordinator's own among them (propagating those would cascade).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

from ..config import CellConfig, UnitConfig
from ..numbers import Cmd, State, names_of, state_name
from ..reasons import Reason
from ..rules import Rules, Trigger, rules_of

#: Source of the unit commands the coordinator sends (the units' remote path).
SOURCE = "remote:coordinator"
#: Source of the interlocks it sets (``<unit>/set_interlock``).
INTERLOCK_SOURCE = "coordinator"
INTERLOCK_RETRY = 0.5  # s between attempts when set_interlock failed
#: s: a lease is checked this long after it ends (a unit is lost when silent for *more* than it)
LEASE_SLACK = 0.001
TRANSITIONS_KEPT = 200
#: Aggregate cell state when the units disagree: the first of these that any online unit is in.
SEVERITY: tuple[State, ...] = (
    State.ABORTING, State.ABORTED,
    State.STOPPING, State.CLEARING, State.STOPPED,
    State.HOLDING, State.HELD,
    State.SUSPENDING, State.SUSPENDED,
    State.UNHOLDING, State.UNSUSPENDING, State.RESETTING, State.STARTING, State.COMPLETING,
    State.IDLE, State.COMPLETE, State.EXECUTE,
)  # fmt: skip
_RANK: dict[int, int] = {int(s): i for i, s in enumerate(SEVERITY)}


def aggregate_state(states: Sequence[int]) -> int:
    """The common state, or the most severe one (:data:`SEVERITY`); 0 for no state."""
    if not states:
        return int(State.UNDEFINED)
    if len(set(states)) == 1:
        return int(states[0])
    return int(min(states, key=lambda s: _RANK.get(s, len(SEVERITY))))


# -- what is read of messages ----------------------------------------------------------------------
class EmLike(Protocol):
    name: str
    active: bool
    online: bool
    blocked: bool
    starved: bool


class InterlockFlags(Protocol):
    blocked: bool
    starved: bool


class StatusLike(Protocol):
    """What the coordinator reads of a unit's ``Status``."""

    stamp: Any
    sequence: int
    state_current: int
    state_current_name: str
    state_requested: int
    unit_mode_current: int
    unit_mode_current_name: str
    unit_mode_change_in_process: bool
    remote_commands_enabled: bool
    commands_valid: Sequence[int]
    equipment_modules: Sequence[Any]
    equipment_interlock: Any
    active_alarms: int
    alarm_banner: str
    stop_reason_id: int


class TransitionLike(Protocol):
    sequence: int
    to_state: int
    command: int
    source: str
    trigger: int


def stamp_ns(stamp: Any) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


# -- effects ---------------------------------------------------------------------------------------
def interlock_failure(want: bool, accepted: bool, result: int, message: str) -> str | None:
    """Why a unit's answer to set_interlock is a failure to retry (None: done). Clearing an
    interlock the unit does not hold from the coordinator (NOTHING_TO_DO) is done."""
    if accepted or (not want and result == Reason.NOTHING_TO_DO):
        return None
    return message


@dataclass(frozen=True)
class Log:
    level: str  #: info | warning
    text: str


@dataclass(frozen=True)
class Call:
    """Call ``service`` of ``unit`` with ``fields``; ``purpose``: ``interlock`` (answer with
    :meth:`Cell.interlock_done`) or ``reaction`` (the answer is only logged)."""

    unit: str
    service: str
    fields: Mapping[str, Any]
    purpose: str
    why: str = ""


@dataclass(frozen=True)
class Resubscribe:
    unit: str


Effect = Log | Call | Resubscribe


# -- units -----------------------------------------------------------------------------------------
@dataclass
class UnitView:
    """What the coordinator knows about one unit."""

    name: str
    config: UnitConfig
    last_seen: float
    online: bool = False
    lost: bool = False  #: reported lost (went silent, or never seen within unit_lease of start)
    status: Any = None  #: the last status (a StatusLike)
    #: (sequence, to_state, command, source, trigger) of recent transitions
    transitions: list[tuple[int, int, int, str, int]] = field(default_factory=list)
    interlock_sent: bool | None = None  #: what the unit holds from us (None: unknown)
    interlock_reason: str = ""
    interlock_pending: bool = False
    interlock_retry_at: float = 0.0
    interlock_error: str = ""
    lost_reason: str = ""
    resubscribed: bool = False  #: since it was lost
    resubscribe_due: bool = False

    @property
    def rules(self) -> Rules:
        return rules_of(self.config)

    def sequence(self) -> int:
        seqs = [self.status.sequence] if self.status is not None else []
        if self.transitions:
            seqs.append(self.transitions[-1][0])
        return max(seqs, default=0)

    def condition(self, which: str) -> bool:
        """Whether one of its active EMs reports ``which`` (blocked / starved)."""
        status = self.status
        return status is not None and any(
            getattr(em, which) for em in status.equipment_modules if em.active
        )

    def valid_commands(self) -> tuple[Cmd, ...]:
        """The commands the rule book accepts in its state and mode, less those its guards refuse
        now (``Status.commands_valid``, the unit's own judgement)."""
        status = self.status
        if status is None:
            return ()
        state, mode = State(status.state_current), status.unit_mode_current
        if mode not in self.config.modes:
            return tuple(Cmd(c) for c in status.commands_valid if 1 <= c <= 10)
        allowed = set(status.commands_valid)
        return tuple(c for c in self.rules.valid_commands(state, mode) if int(c) in allowed)

    def target(self, cmd: Cmd) -> State | None:
        """Where ``cmd`` settles the unit (the rule book's, in its current mode)."""
        mode = self.status.unit_mode_current if self.status is not None else None
        if mode is not None and mode not in self.config.modes:
            mode = None
        return self.rules.command_target(cmd, mode) or self.rules.command_target(cmd)


@dataclass(frozen=True)
class UnitSummaryView:
    """One unit in the cell status."""

    name: str
    online: bool
    status: Any
    em_total: int
    em_online: int
    interlock_suspended: bool
    health: str


@dataclass(frozen=True)
class CellView:
    """The cell status (``CellStatus`` without its stamp)."""

    cell: str
    units: tuple[UnitSummaryView, ...]
    state_current: int
    unit_mode_current: int
    all_online: bool
    busy: bool
    sequence_step: str
    lost_units: tuple[str, ...]
    detail: str
    commands_valid: tuple[int, ...]


class Cell:
    """The units of a cell and the coordinator's view of them (see the module docstring)."""

    def __init__(self, cell: CellConfig, now: float) -> None:
        self.config = cell
        self.coordinator = cell.coordinator
        names = list(cell.units)
        self.start_order = [
            *self.coordinator.start_order,
            *(n for n in names if n not in self.coordinator.start_order),
        ]
        self.stop_order = [
            *self.coordinator.stop_order,
            *(n for n in names if n not in self.coordinator.stop_order),
        ]
        self.started = now
        self.units: dict[str, UnitView] = {n: UnitView(n, cell.units[n], now) for n in names}
        self.hardware_ids = {f"{cell.cell}/{n}": n for n in names}
        self.closed = False

    # -- what arrives ------------------------------------------------------------------------------
    def on_message(self, name: str, topic: str, msg: Any, now: float) -> tuple[bool, list[Effect]]:
        """Something of unit ``name`` arrived on ``topic``: (whether it is news for the waits and
        the status, effects). A transition already held (the latched history delivered again)
        is no news."""
        unit = self.units.get(name)
        if unit is None or self.closed:
            return False, []
        effects: list[Effect] = []
        fresh = topic == "status"
        if fresh and unit.status is not None and stamp_ns(msg.stamp) < stamp_ns(unit.status.stamp):
            fresh = False  # older than the one held (a resubscription's race): ignored
        elif fresh:
            if unit.status is not None and msg.sequence < unit.status.sequence:
                # restarted without its admin data: sequence numbers start again
                unit.transitions = [t for t in unit.transitions if t[0] <= msg.sequence]
            unit.status = msg
        self._seen(unit, fresh, now, effects)
        if topic == "transitions":
            entry = (msg.sequence, msg.to_state, msg.command, msg.source, msg.trigger)
            if unit.transitions and msg.sequence <= unit.transitions[-1][0]:
                if entry in unit.transitions:
                    return False, effects
                unit.transitions = [t for t in unit.transitions if t[0] < msg.sequence]
            unit.transitions.append(entry)
            del unit.transitions[:-TRANSITIONS_KEPT]
        effects += self.reconcile_interlocks(now)
        return True, effects

    def on_diagnostics(
        self, name: str, stale: bool, message: str, now: float
    ) -> tuple[bool, list[Effect]]:
        """The unit's ``packml: <unit>`` entry on /diagnostics: (changed, effects)."""
        unit = self.units.get(name)
        if unit is None or self.closed:
            return False, []
        effects: list[Effect] = []
        if stale:  # a PLC bridge whose PLC is gone
            if unit.online or not unit.lost:
                effects += self.lose(unit, message, now)
                return True, effects + self.reconcile_interlocks(now)
            return False, effects
        was = unit.online
        self._seen(unit, False, now, effects)
        if unit.online != was:
            effects += self.reconcile_interlocks(now)
            return True, effects
        return False, effects

    def _seen(self, unit: UnitView, fresh: bool, now: float, effects: list[Effect]) -> None:
        """Something of the unit arrived: it is alive; online (again) with a status that arrived
        now (``fresh``): after a partition, the status it had before may be stale."""
        unit.last_seen = now
        if unit.online:
            return
        if not fresh:
            if unit.lost and not unit.resubscribed:
                unit.resubscribed = unit.resubscribe_due = True
            return
        unit.online, unit.resubscribed = True, False
        effects.append(
            Log(
                "info",
                f"unit {unit.name} online again" if unit.lost else f"unit {unit.name} online",
            )
        )
        unit.lost, unit.lost_reason = False, ""

    def lose(self, unit: UnitView, why: str, now: float) -> list[Effect]:
        """``unit`` is gone: the other units get ``lost_unit_reaction``."""
        was_online = unit.online
        unit.online, unit.lost, unit.lost_reason = False, True, why
        unit.interlock_sent = None  # unknown until it is back: send again
        last = unit.status.state_current_name if unit.status is not None else "no status"
        effects: list[Effect] = [
            Log("warning", f"unit {unit.name} lost: {why} (last seen in {last})")
        ]
        reaction = self.coordinator.lost_unit_reaction
        if was_online and reaction:
            for other in self.units.values():
                if other is not unit and other.online:
                    effects.append(
                        Call(
                            other.name,
                            "command",
                            {"command": reaction, "source": SOURCE},
                            "reaction",
                            f"{Cmd(reaction).name} to {other.name} because {unit.name} was lost",
                        )
                    )
        return effects

    def tick(self, now: float) -> list[Effect]:
        """Leases, subscriptions due again, interlock retries."""
        if self.closed:
            return []
        effects: list[Effect] = []
        for unit in self.units.values():
            if unit.resubscribe_due:
                unit.resubscribe_due = False
                effects.append(Resubscribe(unit.name))
        lease = self.coordinator.unit_lease
        for unit in self.units.values():
            if unit.online and now - unit.last_seen > lease:
                effects += self.lose(unit, f"no status or diagnostics for {lease:g} s", now)
            elif not unit.online and not unit.lost and now - self.started > lease:
                unit.lost = True
                effects.append(
                    Log(
                        "warning",
                        f"unit {unit.name} not seen within {lease:g} s of the coordinator's start",
                    )
                )
        return effects + self.reconcile_interlocks(now)

    def next_due(self, now: float) -> float:
        """When :meth:`tick` has something to do next (monotonic seconds; ``-inf``: at once,
        ``inf``: nothing): a subscription due again, the lease of an online unit, the start lease
        of a unit not seen yet, an interlock retry. The node arms one timer for it (no polling);
        each of these is done, or moves on, when it is due, so the timer never spins."""
        if self.closed:
            return math.inf
        lease, due = self.coordinator.unit_lease, math.inf
        for unit in self.units.values():
            if unit.resubscribe_due:
                return -math.inf
            if unit.online:
                due = min(due, unit.last_seen + lease + LEASE_SLACK)
            elif not unit.lost:
                due = min(due, self.started + lease + LEASE_SLACK)
            if (
                unit.interlock_error
                and not unit.interlock_pending
                and unit.interlock_retry_at > now
            ):
                due = min(due, unit.interlock_retry_at)
        return due

    def newly_lost(self) -> list[str]:
        return [u.name for u in self.units.values() if u.lost]

    # -- interlocks --------------------------------------------------------------------------------
    def desired_interlocks(self) -> dict[str, list[str]]:
        desired: dict[str, list[str]] = {}
        for rule in self.coordinator.interlocks:
            source = self.units.get(rule.unit)
            if source is not None and source.condition(rule.condition):
                for target in rule.suspend:
                    reasons = desired.setdefault(target, [])
                    if f"{rule.unit} {rule.condition}" not in reasons:
                        reasons.append(f"{rule.unit} {rule.condition}")
        return desired

    def reconcile_interlocks(self, now: float) -> list[Effect]:
        """The set_interlock calls that changed (each answered by :meth:`interlock_done`)."""
        if not self.coordinator.propagate_interlocks or self.closed:
            return []
        desired = self.desired_interlocks()
        out: list[Effect] = []
        for unit in self.units.values():
            reasons = desired.get(unit.name, [])
            want, reason = bool(reasons), "; ".join(reasons)
            if not unit.online or unit.interlock_pending or now < unit.interlock_retry_at:
                continue
            if unit.interlock_sent is want and (not want or reason == unit.interlock_reason):
                continue
            out.append(
                Call(
                    unit.name,
                    "set_interlock",
                    {
                        "active": want,
                        "reason": reason if want else (unit.interlock_reason or "cleared"),
                        "source": INTERLOCK_SOURCE,
                    },
                    "interlock",
                    reason,
                )
            )
        return out

    def interlock_sending(self, name: str) -> None:
        """The node sends the call (the service was there)."""
        self.units[name].interlock_pending = True

    def interlock_done(
        self, name: str, want: bool, reason: str, error: str | None, now: float
    ) -> list[Effect]:
        """The answer of a set_interlock call (``error``: why it failed, None: accepted)."""
        unit = self.units[name]
        unit.interlock_pending = False
        effects: list[Effect] = []
        what = f"interlock on {name} ({reason})" if want else f"clearing the interlock on {name}"
        if error is not None:
            unit.interlock_retry_at = now + INTERLOCK_RETRY
            if error != unit.interlock_error:  # once per distinct problem, not every retry
                unit.interlock_error = error
                effects.append(Log("warning", f"{what} failed: {error}; retrying"))
        else:
            previous = unit.interlock_sent
            unit.interlock_error = ""
            unit.interlock_sent, unit.interlock_reason = want, reason if want else ""
            if want or previous:
                effects.append(
                    Log(
                        "info",
                        f"interlock set on {name}: {reason}"
                        if want
                        else f"interlock cleared on {name}",
                    )
                )
        return effects + self.reconcile_interlocks(now)

    # -- the cell status ---------------------------------------------------------------------------
    def summary(self, unit: UnitView) -> UnitSummaryView:
        s = unit.status
        ems = list(s.equipment_modules) if s is not None else []
        if not unit.online:
            health = "offline"
        elif any(e.active and not e.online for e in ems):
            health = "em lost"
        elif s is not None and s.active_alarms:
            health = "alarm"
        else:
            health = "ok"
        suspended = (
            bool(unit.interlock_sent)
            and s is not None
            and s.state_current in (State.SUSPENDING, State.SUSPENDED)
        )
        return UnitSummaryView(
            unit.name, unit.online, s, len(ems), sum(1 for e in ems if e.online), suspended, health
        )

    def cell_commands_valid(self) -> tuple[int, ...]:
        """The cell commands the units' rules accept now: all or nothing (every online unit
        takes it or is at its target), STOP and ABORT when some unit can take them."""
        units = list(self.units.values())
        if not units or not all(u.online and u.status is not None for u in units):
            return tuple(
                int(c)
                for c in (Cmd.STOP, Cmd.ABORT)
                if any(u.online and c in u.valid_commands() for u in units)
            )
        out = []
        for cmd in Cmd:
            if not cmd:
                continue
            takes = [cmd in u.valid_commands() for u in units]
            there = [u.status.state_requested == u.target(cmd) for u in units]
            if cmd in (Cmd.STOP, Cmd.ABORT):
                ok = any(takes)
            else:
                ok = all(t or h for t, h in zip(takes, there, strict=True)) and any(takes)
            if ok:
                out.append(int(cmd))
        return tuple(out)

    def view(self, busy: bool, step: str, last_result: str) -> CellView:
        units = list(self.units.values())
        present = [u for u in units if u.online and u.status is not None]
        state = aggregate_state([u.status.state_current for u in present])
        modes = {u.status.unit_mode_current for u in present}
        lost = [u.name for u in units if u.lost]
        why = [f"{u.name} ({u.lost_reason})" if u.lost_reason else u.name for u in units if u.lost]
        detail = []
        if not present:
            detail.append("no unit online")
        elif len({u.status.state_current for u in present}) > 1:
            detail.append(
                "mixed: " + ", ".join(f"{u.name} {u.status.state_current_name}" for u in present)
            )
        if lost:
            detail.append(f"lost: {', '.join(why)}")
        held = [f"{u.name} ({u.interlock_reason})" for u in units if u.interlock_sent]
        if held:
            detail.append(f"interlock on {', '.join(held)}")
        if last_result:
            detail.append(f"last: {last_result}")
        return CellView(
            cell=self.config.cell,
            units=tuple(self.summary(u) for u in units),
            state_current=state,
            unit_mode_current=modes.pop() if len(modes) == 1 else 0,
            all_online=all(u.online for u in units),
            busy=busy,
            sequence_step=step,
            lost_units=tuple(lost),
            detail="; ".join(detail),
            commands_valid=self.cell_commands_valid(),
        )

    # -- questions of sequences --------------------------------------------------------------------
    def offline_text(self, unit: UnitView, now: float) -> str:
        return f"{unit.name} is offline (no status or diagnostics for {now - unit.last_seen:.1f} s)"

    def refusals(self, cmd: Cmd, order: Sequence[str], now: float) -> list[tuple[int, str]]:
        """Why units cannot take ``cmd`` now (reason code, sentence): offline, remote commands
        disabled, the command not valid in their state (the rule book, less what the unit's
        guards refuse). Units already at or on their way to the target are fine."""
        from ..reasons import Reason

        out: list[tuple[int, str]] = []
        for name in order:
            unit = self.units[name]
            status = unit.status
            if not unit.online or status is None:
                out.append(
                    (
                        Reason.UNIT_UNAVAILABLE,
                        f"{name} is offline (nothing from it for {now - unit.last_seen:.1f} s)",
                    )
                )
            elif status.state_requested == unit.target(cmd):
                continue
            elif not status.remote_commands_enabled:
                out.append(
                    (
                        Reason.REMOTE_DISABLED,
                        f"{name} does not take remote commands (remote_commands_enabled is false)",
                    )
                )
            elif cmd not in unit.valid_commands():
                valid = names_of([int(c) for c in unit.valid_commands()]) or "none"
                out.append(
                    (
                        Reason.COMMAND_NOT_ALLOWED,
                        f"{name} cannot take {cmd.name} in {status.state_current_name} (valid now: {valid})",
                    )
                )
        return out

    def mode_refusals(self, mode: int, mode_name: str) -> tuple[list[tuple[int, str]], int]:
        """Why units cannot change to the mode now, from their last status and their mode rules;
        and the mode's number."""
        from ..reasons import Reason

        out: list[tuple[int, str]] = []
        number = mode
        for name, unit in self.units.items():
            config = unit.config
            target = config.mode_by_name(mode_name) if mode_name else config.modes.get(mode)
            status = unit.status
            if target is None:
                out.append((Reason.MODE_UNKNOWN, f"{name} has no mode {mode_name or mode}"))
                continue
            number = target.number
            if not unit.online or status is None:
                out.append((Reason.UNIT_UNAVAILABLE, f"{name} is offline"))
            elif not status.remote_commands_enabled:
                out.append(
                    (
                        Reason.REMOTE_DISABLED,
                        f"{name} does not take remote commands (remote_commands_enabled is false)",
                    )
                )
            elif status.unit_mode_change_in_process:
                out.append((Reason.MODE_CHANGE_IN_PROCESS, f"{name} is changing its mode already"))
            elif status.unit_mode_current != target.number:
                why = unit.rules.mode_change_refusal(
                    status.unit_mode_current, target.number, State(status.state_current)
                )
                if why is not None:
                    out.append(
                        (
                            Reason.MODE_CHANGE_NOT_ALLOWED,
                            f"{name} in {status.state_current_name}: {why}",
                        )
                    )
        return out, number

    @staticmethod
    def progress(unit: UnitView, cmd: Cmd | None, seq0: int, target: int) -> str:
        """'reached', the name of the wait state the unit settled in instead, or ''."""
        from ..numbers import WAIT

        later = [t for t in unit.transitions if t[0] > seq0]
        if cmd is not None:
            # From the command's own transition on (older ones may still be in flight).
            mine = next((t[0] for t in later if t[2] == cmd and t[3] == SOURCE), None)
            later = [t for t in later if mine is not None and t[0] >= mine]
        for _, to_state, _, _, trigger in later:
            if to_state == target:
                return "reached"
            if to_state in WAIT and trigger != Trigger.MODE:
                return state_name(to_state)
        status = unit.status
        if status is not None and status.state_current == target and status.sequence > seq0:
            return "reached"
        if cmd is None and status is not None and status.state_current == target:
            return "reached"
        return ""
