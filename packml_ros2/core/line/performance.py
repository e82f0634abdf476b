"""Line performance: what each unit and the line spend their time on, stop episodes with their
root cause, counts — turned into facts for the :class:`~.ledger.Ledger`.

Pure and deterministic: every input carries the line's clock (``now``, integer ns) and the unit's
own stamps; the same inputs in the same order give the same facts and episodes (a replay from a
bag reproduces them exactly).

Per unit, the **steps** come from its transitions (reliable, in order; the latched history fills
what came before the coordinator started); its status adds what a step's transition does not
carry (the StopReason ID, its EMs' Blocked/Starved) and tells the state at first contact. A unit's
time is cut into segments at each step and each change of presence; a segment's bucket is decided
when it closes (what arrived meanwhile for the same step, such as its stop reason, counts). The
line produces while every unit is online, in Production and in Execute; its time is running,
a changeover while a unit is in a changeover mode, an episode (attributed to the episode's root
cause) or, outside episodes, attributed to the first unit of the line order that is not running.
See :mod:`.episodes` and :mod:`.losses`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

from ..interlocks import INTERLOCK_KIND
from ..modes import GROUPS
from ..numbers import Mode, State, command_name, state_name
from ..rules import Trigger
from ..stopreason import planned_stop
from .calendar import Calendar
from .config import LineConfig
from .episodes import (
    CELL,
    INTERNAL,
    OWN_BLOCKED,
    OWN_STARVED,
    PENDING,
    PROPAGATED,
    Departure,
    Episode,
    Root,
)
from .ledger import Count, Fact, Ledger, Segment
from .losses import (
    BLOCKED,
    CHANGEOVER,
    HELD,
    LINE,
    PLANNED,
    RUNNING,
    STARVED,
    UNPLANNED,
    at_speed,
)

HOLD_STATES = GROUPS["HOLD"]  # (the state groups a configuration names: one declaration)
SUSPEND_STATES = GROUPS["SUSPEND"]
#: Source of the coordinator's commands to units, and of its interlocks.
COORDINATOR_SOURCE = "remote:coordinator"
INTERLOCK_SOURCE = "coordinator"
OFFLINE = "offline"
EPISODES_KEPT = 50  # closed episodes kept in memory (all of them are in the store)
HISTORY = 200  # transitions kept from before a unit's first status
AHEAD_WAIT = 2 * 10**9  # ns a status waits for the transitions it is ahead of


class UnitLike(Protocol):
    """What performance reads of a unit's configuration."""

    @property
    def mach_design_speed(self) -> float: ...
    @property
    def planned_stop_ids(self) -> tuple[int, int]: ...
    @property
    def modes(self) -> Mapping[int, Any]: ...
    @property
    def equipment_modules(self) -> Sequence[Any]: ...


@dataclass(frozen=True)
class StatusSnap:
    """What performance reads of a unit's Status."""

    sequence: int
    time: int  #: its stamp (ns): the time of the step it shows
    state: int
    mode: int
    stop_reason_id: int = 0
    blocked: bool = False  #: an active EM of the unit reports Blocked
    starved: bool = False


@dataclass(frozen=True)
class TransitionSnap:
    """What performance reads of a TransitionEvent."""

    sequence: int
    time: int
    from_state: int
    to_state: int
    from_mode: int
    to_mode: int
    trigger: int
    command: int = 0
    source: str = ""
    detail: str = ""


@dataclass
class Step:
    """A unit's state since a transition (sequence)."""

    sequence: int
    time: int
    state: int
    mode: int
    from_state: int = 0
    trigger: int = -1  #: -1: only its status arrived so far
    command: int = 0
    source: str = ""
    detail: str = ""
    reason_id: int = 0  #: the StopReason ID at this step (the previous step's until told)


@dataclass
class Tracker:
    """What performance knows of one unit."""

    name: str
    position: int
    design: float
    planned_ids: tuple[int, int]
    step: Step | None = None
    started: int | None = None  #: when its accounting began (first contact)
    online: bool = False
    lost_why: str = ""
    since: int = 0  #: start of the open segment
    cause: Departure | None = None  #: why it is out of Execute
    blocked: bool = False
    starved: bool = False
    processed: int | None = None  #: AccCount totals at the last admin data
    defective: int | None = None
    last_alive: int = 0
    restart_time: int = 0
    #: the StopReason of its last admin data and when it was set (it may arrive before the
    #: status that opens the episode it explains)
    stop_reason: dict[str, Any] | None = None
    stop_reason_at: int = 0
    #: transitions that arrived before the first status (the latched history), in order
    pending: list[TransitionSnap] = field(default_factory=list)
    #: a status ahead of the transitions (sequence, when it arrived): applied if they never come
    ahead: tuple[StatusSnap, int] | None = None

    def producing(self) -> bool:
        s = self.step
        return (
            self.online and s is not None and s.mode == Mode.PRODUCTION and s.state == State.EXECUTE
        )

    def to_dict(self) -> dict[str, Any]:
        d = {
            k: v for k, v in self.__dict__.items() if k not in ("step", "cause", "pending", "ahead")
        }
        d["step"] = None if self.step is None else dict(self.step.__dict__)
        d["cause"] = None if self.cause is None else self.cause.to_dict()
        d["planned_ids"] = list(self.planned_ids)
        return d

    def restore(self, d: Mapping[str, Any]) -> None:
        for key in (
            "started",
            "online",
            "lost_why",
            "since",
            "blocked",
            "starved",
            "processed",
            "defective",
            "last_alive",
            "restart_time",
            "stop_reason",
            "stop_reason_at",
        ):
            if key in d:
                setattr(self, key, d[key])
        self.step = None if d.get("step") is None else Step(**d["step"])
        self.cause = None if d.get("cause") is None else Departure.from_dict(d["cause"])


def step_label(s: Step, names: Mapping[int, str]) -> str:
    """Why the unit is where step ``s`` took it, one line."""
    t, detail, source = s.trigger, s.detail, s.source
    if t == Trigger.ALARM:
        alarm = source.partition(":")[2] if source.startswith("alarm:") else ""
        return f"alarm {alarm}: {detail}" if alarm and detail else detail or source or "alarm"
    if t == Trigger.COMMAND:
        if source == "plc":
            return detail or f"{command_name(s.command)} at the PLC"
        return f"{command_name(s.command)} by {source or 'operator'}" if s.command else detail
    if t == Trigger.INTERLOCK:
        return detail or "interlock"
    if t == Trigger.EM_LOST:
        return f"EM lost: {detail}" if detail else "EM lost"
    if t == Trigger.TIMEOUT:
        return f"timeout: {detail}" if detail else "timeout"
    if t == Trigger.STATE_COMPLETE:
        return f"{state_name(s.from_state).lower()} complete"
    if t == Trigger.RESTART:
        return "unit restarted"
    if t == Trigger.MODE:
        return f"mode {names.get(s.mode, s.mode)} by {source or 'operator'}"
    return detail or state_name(s.state)


class Performance:
    """See the module docstring. Inputs: :meth:`status`, :meth:`transition`, :meth:`admin`,
    :meth:`online`, :meth:`lost`, :meth:`cell_command`, :meth:`interlock`, :meth:`reset`,
    :meth:`tick`; outputs: :meth:`take` (new facts and changed episodes), :meth:`windows`."""

    def __init__(
        self, config: LineConfig, units: Mapping[str, UnitLike], ledger: Ledger | None = None
    ) -> None:
        self.config = config
        self.calendar: Calendar = config.calendar
        self.order = config.order or tuple(units)
        self.units = units
        self.output = config.output_unit or self.order[-1]
        self.trackers: dict[str, Tracker] = {
            name: Tracker(
                name,
                self.order.index(name) if name in self.order else i,
                units[name].mach_design_speed,
                units[name].planned_stop_ids,
            )
            for i, name in enumerate(units)
        }
        self.ledger = ledger or Ledger()
        self.changeover_modes = frozenset(m.lower() for m in config.changeover_modes)
        self.started: int | None = None  #: when the line's accounting began
        self.line_since = 0
        self.producing = False
        self.episode: Episode | None = None
        self.closed: list[Episode] = []  #: the last closed episodes (newest last)
        self.next_id = 1
        self.caller = ""  #: who asked the last cell command, and which
        self.cell_cmd = 0
        self.sent: dict[str, set[str]] = {}  #: unit -> interlock reasons the coordinator set
        self.now = 0
        self._facts: list[Fact] = []
        self._episodes: dict[int, Episode] = {}  # changed since the last take()
        self._departed: list[Departure] = []

    # ==============================================================================================
    # Inputs
    # ==============================================================================================
    def status(self, now: int, unit: str, s: StatusSnap) -> None:
        tr = self.trackers[unit]
        self._alive(now, tr)
        tr.blocked, tr.starved = s.blocked, s.starved
        step = tr.step
        if step is None:
            self._first_contact(now, tr, s)
        elif s.sequence == step.sequence:
            tr.ahead = None
            if step.reason_id != s.stop_reason_id:
                step.reason_id = s.stop_reason_id
                self._refine(tr)
        elif s.sequence < step.sequence and s.time > step.time:
            # restarted without its admin data: its sequence numbers begin again
            tr.ahead = None
            self._step(
                now, tr, Step(s.sequence, s.time, s.state, s.mode, reason_id=s.stop_reason_id)
            )
        elif s.sequence > step.sequence:
            tr.ahead = (s, now)  # its transitions are on their way (else: tick applies it)

    def transition(self, now: int, unit: str, t: TransitionSnap) -> None:
        tr = self.trackers[unit]
        heard = tr.last_alive
        self._alive(now, tr)
        step = tr.step
        if step is None:
            tr.pending.append(t)
            del tr.pending[:-HISTORY]
            return
        # a restart not seen yet (a unit restarted without its store numbers from 1 again); the
        # latched history a restarted coordinator receives holds old ones: not after the step
        restart = t.trigger == Trigger.RESTART and t.time > max(tr.restart_time, step.time)
        if t.sequence == step.sequence and step.trigger < 0 and t.to_state == step.state:
            self._describe(step, t)  # the status of this step came first
            if t.trigger == Trigger.RESTART:
                tr.restart_time = max(tr.restart_time, t.time)
            self._refine(tr)
        elif t.sequence > step.sequence or restart:
            if restart:
                tr.restart_time = t.time
                gone = max(tr.since, min(heard, t.time))
                if tr.online and gone < t.time:  # gone since it was last heard of
                    self._before(gone, self._changeover(tr, tr.step))
                    self._close_unit(tr, gone)
                    tr.online, tr.lost_why = False, "restarted"
                    self._close_unit(tr, t.time)
                    tr.online, tr.lost_why = True, ""
            # a restarted unit's stop reason is not the one before (a crash replaces it): unknown
            # (not planned) until its status says it
            reason = 0 if restart else step.reason_id
            new = Step(t.sequence, t.time, t.to_state, t.to_mode, reason_id=reason)
            self._describe(new, t)
            self._step(now, tr, new)
            if tr.ahead is not None and tr.ahead[0].sequence <= new.sequence:
                tr.ahead = None

    def admin(
        self,
        now: int,
        unit: str,
        t: int,
        processed: int,
        defective: int,
        stop_reason: Mapping[str, Any] | None,
    ) -> None:
        """Admin data: ``processed``/``defective`` are the AccCount totals; ``stop_reason`` the
        StopReason (id, value, message, category, source, em) or None."""
        tr = self.trackers[unit]
        self._alive(now, tr)
        if tr.processed is not None and tr.defective is not None and tr.started is not None:
            dp, dd = processed - tr.processed, defective - tr.defective
            if dp < 0 or dd < 0:  # counters of a unit restarted without its admin data
                dp, dd = max(processed, 0), max(defective, 0)
            if dp or dd:
                at = max(t, tr.started)
                self._count(unit, at, dp, dd, tr.design)
                if unit == self.output and self.started is not None and at >= self.started:
                    self._count(LINE, at, dp, dd, tr.design)
        tr.processed, tr.defective = processed, defective
        if not stop_reason:
            tr.stop_reason = None
            return  # (the root unit's reason, if any, was taken when it came or the root changed)
        tr.stop_reason, tr.stop_reason_at = dict(stop_reason), int(stop_reason.get("time", t))
        if self.episode is not None:
            self._explain(self.episode)

    def _explain(self, ep: Episode) -> None:
        """The episode's StopReason: its root unit's, when set at most 1 s before it departed.
        Admin data and status are separate topics, so either may come first."""
        d = ep.root(self.order).departure
        tr = None if d is None else self.trackers.get(d.unit)
        if d is None or tr is None or not tr.stop_reason:
            return
        if tr.stop_reason_at >= d.time - 10**9 and ep.stop_reason != tr.stop_reason:
            ep.stop_reason = dict(tr.stop_reason)
            self._changed(ep)

    def online(self, now: int, unit: str) -> None:
        """Something of ``unit`` arrived after it was lost (its status follows)."""
        tr = self.trackers[unit]
        if tr.online or tr.step is None:
            tr.last_alive = now
            return
        self._presence(now, tr, True, "")

    def lost(self, now: int, unit: str, why: str) -> None:
        tr = self.trackers[unit]
        if tr.online:
            self._presence(now, tr, False, why)

    def cell_command(self, now: int, command: int, caller: str) -> None:
        self.cell_cmd, self.caller = command, caller
        self.now = max(self.now, now)

    def interlock(self, now: int, unit: str, active: bool, reason: str) -> None:
        """The coordinator sets (or clears) an interlock on ``unit`` with ``reason``."""
        if active:
            reasons = self.sent.setdefault(unit, set())
            reasons.add(reason)
            if len(reasons) > 64:
                reasons.pop()
        self.now = max(self.now, now)

    def reset(self, now: int) -> None:
        """Start the since-reset window now."""
        self.ledger.reset_now(now)
        self.now = max(self.now, now)

    def tick(self, now: int) -> None:
        """The clock moved (a publication of losses, a lease check): a status whose transitions
        did not follow within :data:`AHEAD_WAIT` is taken as the unit's step."""
        self.now = max(self.now, now)
        for tr in self.trackers.values():
            if tr.ahead is not None and now - tr.ahead[1] >= AHEAD_WAIT:
                s, _ = tr.ahead
                tr.ahead = None
                if tr.step is None or s.sequence > tr.step.sequence:
                    self._step(
                        now,
                        tr,
                        Step(s.sequence, s.time, s.state, s.mode, reason_id=s.stop_reason_id),
                    )

    # ==============================================================================================
    # Outputs
    # ==============================================================================================
    def take(self) -> tuple[list[Fact], list[Episode]]:
        """The facts closed and the episodes changed since the last call (copies)."""
        facts, self._facts = self._facts, []
        episodes = [e.copy() for e in self._episodes.values()]
        self._episodes = {}
        return facts, episodes

    def root(self, episode: Episode) -> Root:
        return episode.root(self.order)

    def open_parts(self, now: int) -> list[Fact]:
        """The open segments up to ``now``, as facts (not kept)."""
        out: list[Fact] = []
        for tr in self.trackers.values():
            if tr.started is not None and tr.step is not None and now > tr.since:
                bucket, reason = self.unit_class(tr)
                out += self._pieces(tr.name, tr.since, now, bucket, reason)
        if self.started is not None and now > self.line_since:
            bucket, reason = self.line_class()
            out += self._pieces(LINE, self.line_since, now, bucket, reason)
        return out

    def windows(self, which: str, now: int) -> dict[str, Any]:
        """Totals per scope of a running window (:meth:`.Ledger.totals`)."""
        return dict(self.ledger.totals(which, now, self.open_parts(now)))

    def design(self, scope: str) -> float:
        return self.trackers[self.output if scope == LINE else scope].design

    # ==============================================================================================
    # Classification
    # ==============================================================================================
    def unit_class(self, tr: Tracker) -> tuple[str, str]:
        """(bucket, reason) of the unit's open segment, as things stand."""
        s = tr.step
        if not tr.online or s is None:
            return UNPLANNED, OFFLINE
        if s.mode != Mode.PRODUCTION:
            name = self._mode_name(tr, s.mode)
            return self._mode_bucket(name), f"{name} mode"
        if s.state == State.EXECUTE:
            return RUNNING, ""
        cause = tr.cause
        reason = (
            cause.label
            if cause is not None and cause.label
            else step_label(s, self._mode_names(tr))
        )
        return self._bucket(tr, s, cause), reason

    def _bucket(self, tr: Tracker, s: Step, cause: Departure | None) -> str:
        if s.state in HOLD_STATES:
            return HELD
        if s.state in SUSPEND_STATES and cause is not None:
            if cause.kind == OWN_BLOCKED or (
                cause.kind == PROPAGATED and cause.condition == "blocked"
            ):
                return BLOCKED
            if cause.kind == OWN_STARVED or (
                cause.kind == PROPAGATED and cause.condition == "starved"
            ):
                return STARVED
        if planned_stop(tr.planned_ids, s.reason_id, s.mode, s.state):
            return PLANNED
        return UNPLANNED

    def line_class(self) -> tuple[str, str]:
        """(bucket, reason) of the line's open segment: running; a changeover while a unit (the
        first of the line order) is in a changeover mode; the episode's root cause; or the first
        unit of the line order that is not running."""
        if self.producing:
            return RUNNING, ""
        for name in self.order:
            tr = self.trackers[name]
            if tr.online and self._changeover(tr, tr.step):
                bucket, reason = self.unit_class(tr)
                return bucket, f"{name}: {reason}"
        if self.episode is not None:
            root = self.episode.root(self.order)
            return root.bucket, f"{root.unit or 'cell'}: {root.reason}"
        for name in self.order:
            tr = self.trackers[name]
            if not tr.producing():
                bucket, reason = self.unit_class(tr)
                return bucket, f"{name}: {reason}"
        return UNPLANNED, "line"

    def _mode_name(self, tr: Tracker, mode: int) -> str:
        return str(getattr(self.units[tr.name].modes.get(mode), "name", mode))

    def _mode_bucket(self, name: str) -> str:
        """The bucket of the time out of Production in mode ``name``: a changeover mode's is
        ``changeover`` (``line.changeover_modes``), any other's ``planned_stop``."""
        return CHANGEOVER if name.lower() in self.changeover_modes else PLANNED

    def _changeover(self, tr: Tracker, s: Step | None) -> bool:
        """Whether ``s`` is a step of ``tr`` in a changeover mode."""
        return (
            s is not None
            and s.mode != Mode.PRODUCTION
            and self._mode_bucket(self._mode_name(tr, s.mode)) == CHANGEOVER
        )

    def _mode_names(self, tr: Tracker) -> dict[int, str]:
        return {n: getattr(m, "name", str(n)) for n, m in self.units[tr.name].modes.items()}

    def _classify(
        self, tr: Tracker, d: Departure, lost: str = "", step: Step | None = None
    ) -> None:
        """How ``d`` left Execute, from what is known of its step."""
        s = step or tr.step
        if lost:
            d.kind, d.label, d.bucket = INTERNAL, f"unit lost ({lost})", UNPLANNED
            return
        if s is None or s.sequence != d.sequence:
            return
        d.trigger, d.command, d.source, d.detail, d.reason_id = (
            s.trigger,
            s.command,
            s.source,
            s.detail,
            s.reason_id,
        )
        d.label = step_label(s, self._mode_names(tr))
        if s.mode != Mode.PRODUCTION:
            d.kind = INTERNAL if s.trigger >= 0 else PENDING
            d.bucket = self._mode_bucket(self._mode_name(tr, s.mode))
            return
        if s.trigger < 0:
            d.kind = PENDING
        elif s.trigger == Trigger.INTERLOCK and self._propagated(tr, s):
            first = s.detail.split(";")[0].strip()
            cause_unit, _, condition = first.rpartition(" ")
            d.kind, d.cause_unit, d.condition = PROPAGATED, cause_unit, condition
        elif s.trigger == Trigger.INTERLOCK and "blocked" in s.detail:
            d.kind = OWN_BLOCKED
        elif s.trigger == Trigger.INTERLOCK and "starved" in s.detail:
            d.kind = OWN_STARVED
        elif (
            s.state in SUSPEND_STATES
            and s.source != COORDINATOR_SOURCE
            and (tr.blocked or tr.starved)
        ):
            d.kind = OWN_BLOCKED if tr.blocked else OWN_STARVED
        elif s.source == COORDINATOR_SOURCE:
            gone = [u.name for u in self.trackers.values() if not u.online and u.step is not None]
            if gone:
                d.kind, d.cause_unit, d.label = PROPAGATED, gone[0], f"{gone[0]} lost"
            else:
                d.kind = CELL
                who = f" ({self.caller})" if self.caller else ""
                d.label = f"cell {command_name(s.command or self.cell_cmd)}{who}"
        else:
            d.kind = INTERNAL
        d.bucket = self._bucket(tr, s, d)

    def _propagated(self, tr: Tracker, s: Step) -> bool:
        """Whether an interlock step of ``tr`` is the coordinator's: its source names the holder
        (``interlock:coordinator``; ``interlock:em:<name>`` is the unit's own EM). Units of input
        log schema 1 said ``interlock`` for both: then by the reason the coordinator sent (a PLC
        bridge names the setter itself: ``coordinator``)."""
        kind, _, holder = s.source.partition(":")
        if kind == INTERLOCK_KIND and holder:
            return holder == INTERLOCK_SOURCE
        return s.source == INTERLOCK_SOURCE or s.detail in self.sent.get(tr.name, ())

    # ==============================================================================================
    # Inside
    # ==============================================================================================
    def _alive(self, now: int, tr: Tracker) -> None:
        tr.last_alive = now
        self.now = max(self.now, now)

    def _describe(self, step: Step, t: TransitionSnap) -> None:
        step.from_state, step.trigger, step.command = t.from_state, t.trigger, t.command
        step.source, step.detail = t.source, t.detail

    def _start(self, now: int, tr: Tracker) -> None:
        if tr.started is None:
            tr.started = now
            tr.since = now
            tr.online = True

    def _first_contact(self, now: int, tr: Tracker, s: StatusSnap) -> None:
        """The first status of a unit: its step now; the transitions that came before it (the
        latched history) describe that step and why it is not in Execute; later ones follow."""
        history = sorted(tr.pending, key=lambda t: t.sequence)
        tr.pending = []
        self._start(now, tr)
        step = Step(s.sequence, s.time, s.state, s.mode, reason_id=s.stop_reason_id)
        for t in history:
            if t.trigger == Trigger.RESTART:
                tr.restart_time = max(tr.restart_time, t.time)
            if t.sequence == s.sequence and t.to_state == s.state:
                self._describe(step, t)
        tr.step = step
        if step.state != State.EXECUTE:
            # why it is not in Execute: its last departure from it, else how it began
            left = [
                t for t in history if t.sequence <= s.sequence and t.from_state == State.EXECUTE
            ]
            first = (
                left[-1] if left else next((t for t in history if t.sequence <= s.sequence), None)
            )
            if first is not None:
                old = Step(
                    first.sequence,
                    first.time,
                    first.to_state,
                    first.to_mode,
                    reason_id=s.stop_reason_id,
                )
                self._describe(old, first)
            else:
                old = step
            d = Departure(tr.name, old.time, old.sequence, old.state)
            self._classify(tr, d, step=old)
            tr.cause = d
        self._line(now)
        for t in history:
            if t.sequence > s.sequence:
                self.transition(now, tr.name, t)

    def _step(self, now: int, tr: Tracker, new: Step) -> None:
        """``tr`` takes step ``new`` (at its own time, not before its open segment)."""
        self._start(now, tr)
        at = max(new.time, tr.since)
        was = tr.producing()
        self._before(at, tr.online and self._changeover(tr, tr.step) != self._changeover(tr, new))
        self._close_unit(tr, at)
        tr.step = new
        if tr.producing():
            tr.cause = None
        elif was:
            self._depart(tr, at)
        self._line(at)

    def _presence(self, now: int, tr: Tracker, online: bool, why: str) -> None:
        was = tr.producing()
        self._before(now, self._changeover(tr, tr.step))
        self._close_unit(tr, now)
        tr.online, tr.lost_why = online, why
        if not online and was:
            self._depart(tr, now, lost=why or "no sign of life")
        elif online and tr.producing():
            tr.cause = None
        self._line(now)

    def _depart(self, tr: Tracker, at: int, lost: str = "") -> None:
        s = tr.step
        d = Departure(tr.name, at, s.sequence if s else 0, s.state if s else 0)
        self._classify(tr, d, lost)
        tr.cause = d
        if self.started is not None:
            self._departed.append(d)

    def _refine(self, tr: Tracker) -> None:
        """New information on the unit's current step (its transition or its stop reason)."""
        d = tr.cause
        if d is None or (d.kind == INTERNAL and d.label.startswith("unit lost")):
            return
        self._classify(tr, d)
        ep = self.episode
        if ep is not None and any(x is d for x in ep.departures):
            self._changed(ep)

    def _close_unit(self, tr: Tracker, at: int) -> None:
        if tr.started is None or tr.step is None or at <= tr.since:
            tr.since = max(tr.since, at) if tr.started is not None else tr.since
            return
        bucket, reason = self.unit_class(tr)
        self._facts_out(self._pieces(tr.name, tr.since, at, bucket, reason))
        tr.since = at

    def _before(self, at: int, changeover: bool = False) -> None:
        """A unit is about to change at ``at``: the line's segment outside an episode ends (its
        attribution is the units' as they were), in an episode too when the change begins or
        ends a unit's changeover (``changeover``: the line's time is a changeover meanwhile)."""
        if self.started is not None and not self.producing and (self.episode is None or changeover):
            self._close_line(max(at, self.line_since))

    def _close_line(self, at: int) -> None:
        if at > self.line_since:
            bucket, reason = self.line_class()
            self._facts_out(self._pieces(LINE, self.line_since, at, bucket, reason))
        self.line_since = max(self.line_since, at)

    def _line(self, at: int) -> None:
        """After a change at ``at``: does the line produce, does an episode open or end."""
        departed, self._departed = self._departed, []
        if self.started is None:
            if all(t.started is not None for t in self.trackers.values()):
                self.started = self.line_since = at
                self.producing = self._all_producing()
            return
        at = max(at, self.line_since)
        producing = self._all_producing()
        ep = self.episode
        if ep is not None:
            for d in departed:
                ep.departures.append(d)
                self._changed(ep)
            if departed:
                self._explain(ep)
            if producing:
                self._close_line(at)
                ep.end = at
                self._changed(ep)
                self.closed.append(ep)
                del self.closed[:-EPISODES_KEPT]
                self.episode = None
        elif self.producing and not producing:
            self._close_line(at)
            ep = self.episode = Episode(self.next_id, at, None, list(departed))
            self.next_id += 1
            self._changed(ep)
            self._explain(ep)
        elif producing and not self.producing:
            self._close_line(at)
        self.producing = producing

    def _all_producing(self) -> bool:
        return all(t.producing() for t in self.trackers.values())

    def _changed(self, ep: Episode) -> None:
        self._episodes[ep.id] = ep

    def _pieces(self, scope: str, a: int, b: int, bucket: str, reason: str) -> list[Fact]:
        out: list[Fact] = []
        for p in self.calendar.pieces(a, b):
            if p.planned and bucket != RUNNING:
                out.append(Segment(scope, p.start, p.end, PLANNED, p.planned, p.shift))
            else:
                out.append(Segment(scope, p.start, p.end, bucket, reason, p.shift))
        return out

    def _count(self, scope: str, at: int, dp: int, dd: int, design: float) -> None:
        inst = self.calendar.instance_at(at)
        fact = Count(
            scope,
            at,
            dp,
            dd,
            at_speed(dp, design),
            at_speed(dp - dd, design),
            inst.key if inst else "",
        )
        self._facts_out([fact])

    def _facts_out(self, facts: list[Fact]) -> None:
        if facts:
            self.ledger.add(facts)
            self._facts.extend(facts)

    # ==============================================================================================
    # Persistence
    # ==============================================================================================
    def document(self) -> dict[str, Any]:
        """The open state (what the facts do not hold): trackers, the line, the open episode."""
        return {
            "trackers": {n: t.to_dict() for n, t in self.trackers.items()},
            "started": self.started,
            "line_since": self.line_since,
            "producing": self.producing,
            "episode": self.episode.to_dict() if self.episode else None,
            "next_id": self.next_id,
            "caller": self.caller,
            "cell_cmd": self.cell_cmd,
            "sent": {u: sorted(r) for u, r in self.sent.items()},
            "now": self.now,
        }

    def restore(self, doc: Mapping[str, Any], closed: Sequence[Episode] = ()) -> None:
        for name, d in doc.get("trackers", {}).items():
            if name in self.trackers:
                self.trackers[name].restore(d)
        self.started = doc.get("started")
        self.line_since = int(doc.get("line_since", 0))
        self.producing = bool(doc.get("producing", False))
        ep = doc.get("episode")
        self.episode = Episode.from_dict(ep) if ep else None
        if self.episode is not None:  # the open episode's departures are the units' causes
            for d in self.episode.departures:
                tr = self.trackers.get(d.unit)
                if tr is not None and tr.cause is not None and tr.cause.time == d.time:
                    self.episode.departures[self.episode.departures.index(d)] = tr.cause
        self.next_id = int(doc.get("next_id", 1))
        self.caller = str(doc.get("caller", ""))
        self.cell_cmd = int(doc.get("cell_cmd", 0))
        self.sent = {u: set(r) for u, r in doc.get("sent", {}).items()}
        self.now = int(doc.get("now", 0))
        self.closed = [e.copy() for e in closed][-EPISODES_KEPT:]


__all__ = [
    "COORDINATOR_SOURCE",
    "Performance",
    "StatusSnap",
    "Step",
    "Tracker",
    "TransitionSnap",
    "step_label",
]
