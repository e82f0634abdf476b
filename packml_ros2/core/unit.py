"""The PackML unit engine: state machine, modes, EM aggregation, alarms, times and counters.

A :class:`Unit` is pure Python: it takes its clock as a parameter and never looks at wall time
itself. Every input (a command, a mode request, an EM report, an alarm...) first advances the engine
to the clock's time, firing due deadlines (timeouts, dwell, periodic admin and saves) *at their own
times*; the results depend only on the inputs and their times, so replaying recorded inputs on the
recorded clock reproduces the outputs exactly.

Outputs are queued and taken with :meth:`Unit.drain`: transitions, status and alarm-list changes,
admin snapshots due, and log lines. The ROS node (``packml_ros2.unit_node``) publishes them.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any, NamedTuple

from .alarms import AlarmDef, AlarmEvent, AlarmManager, Kind
from .config import Descriptor, Ingredient, Product, UnitConfig
from .counters import Counters
from .equipment import Equipment, EquipmentModule
from .modes import ModeDef, mode_change_refusal, resolve
from .numbers import (
    ACTING,
    NUM_STATES,
    Cmd,
    Mode,
    State,
    command_name,
    names_of,
    state_name,
)
from .packtags import AdminView, StatusView, build_admin, build_status
from .persistence import Store
from .reasons import Answer, Reason
from .times import ModeStateTimes

S, C = State, Cmd
Clock = Callable[[], float]


class Trigger(IntEnum):
    """Why a transition happened; mirrors ``packml_interfaces/msg/TransitionEvent`` TRIGGER_*."""

    COMMAND = 0
    STATE_COMPLETE = 1
    ALARM = 2
    INTERLOCK = 3
    SKIP = 4
    MODE = 5
    EM_LOST = 6
    TIMEOUT = 7
    RESTART = 8


#: Priority in one evaluation step: Abort > Stop > Hold > Suspend > other commands (PACKML.md 2),
#: then mode changes, then State Complete reports.
PRIORITY: dict[int, int] = {C.ABORT: 0, C.STOP: 1, C.HOLD: 2, C.SUSPEND: 3}
OTHER_COMMANDS, MODE_REQUESTS, STATE_COMPLETE_REPORTS = 4, 5, 6
#: Commands that start motion: refused while an active EM is missing, a reacting alarm is active
#: or (Unsuspend) a line interlock still holds the unit.
MOTION = frozenset({C.RESET, C.START, C.UNHOLD, C.UNSUSPEND})
#: Commands refused while a reacting alarm is active: motion, and Clear while an alarm with the
#: Abort reaction is (``alarms.BLOCKED_BY_REACTION`` decides per reaction).
ALARM_GUARDED = MOTION | {C.CLEAR}
#: Fault commands: valid from (nearly) every state, also while a mode change is in process (the
#: change is then abandoned: PACKML.md 2, "Abort -> Aborting from every state ...").
FAULT_COMMANDS = frozenset({C.ABORT, C.STOP})
#: Fault-recovery states: EMs that went offline are excused from State Complete here.
EXCUSE_OFFLINE = frozenset({S.STOPPING, S.ABORTING, S.CLEARING})
#: Entering one of these records the StopReason (first event only) ...
STOP_STATES = frozenset({S.STOPPING, S.ABORTING, S.HOLDING, S.SUSPENDING})
#: ... which is re-armed when production is started again.
REARM_STATES = frozenset({S.RESETTING, S.STARTING, S.UNHOLDING, S.UNSUSPENDING})
#: Where the unit settles from each state (``Status.StateRequested``); wait states: themselves.
SETTLE: dict[State, State] = {
    S.STARTING: S.EXECUTE,
    S.UNHOLDING: S.EXECUTE,
    S.UNSUSPENDING: S.EXECUTE,
    S.EXECUTE: S.EXECUTE,
    S.RESETTING: S.IDLE,
    S.COMPLETING: S.COMPLETE,
    S.HOLDING: S.HELD,
    S.SUSPENDING: S.SUSPENDED,
    S.STOPPING: S.STOPPED,
    S.ABORTING: S.ABORTED,
    S.CLEARING: S.STOPPED,
}
#: OMAC stop-reason IDs (Beckhoff E_AlarmID ranges) for stops that were not alarms.
STOP_ID_OPERATOR = 33  # operator action: cycle stop button
STOP_ID_REMOTE = 4006  # out of service: remote stop requested
STOP_ID_BLOCKED = 3002  # downstream: discharge blocked
STOP_ID_STARVED = 2499  # upstream: undefined upstream reason
STOP_ID_SHUTDOWN = 1000  # machine internal, vendor defined: the unit's own process shut down
#: What entering a state does besides the transition itself (bit flags, see _entry_actions).
_RESET_ALARMS, _CLEAR_FIRST_OUT, _REARM, _STOP = 1, 2, 4, 8
ENTRY_FLAGS: dict[State, int] = {
    S.RESETTING: _RESET_ALARMS | _REARM,
    S.CLEARING: _RESET_ALARMS,
    S.STARTING: _CLEAR_FIRST_OUT | _REARM,
    S.UNHOLDING: _REARM,
    S.UNSUSPENDING: _REARM,
    S.STOPPING: _STOP,
    S.ABORTING: _STOP,
    S.HOLDING: _STOP,
    S.SUSPENDING: _STOP,
}
#: States whose entry only re-arms the stop reason when there are no alarms to reset and no
#: first-outs to clear (the common case, inlined in Unit._transition).
_REARMING = frozenset(s for s, f in ENTRY_FLAGS.items() if f & _REARM and not f & _STOP)
#: A stop is planned (OEE) only while the unit stands in one of these.
PLANNED_STOP_STATES = frozenset({S.STOPPED, S.IDLE, S.STOPPING})
MODE_CHANGE_NOT_ALLOWED_SECONDS = 3.0
#: Periodic deadlines (admin, save) missed by more than this many periods (the clock jumped, e.g.
#: NTP after boot) are not replayed one by one: the next one is the last period point before now.
MAX_CATCH_UP = 100
#: Status changes that are not transitions (EM progress, alarms, speed) are published at most
#: this often; transitions and mode events are published at once.
STATUS_COALESCE = 0.05
#: Admin is published periodically (admin_period) and after discrete changes (transitions, counts,
#: alarms, resets), at most this often.
ADMIN_COALESCE = 0.25
_STATES = tuple(State)
_CMDS = tuple(Cmd)
_REPORT_OK = Answer(True, Reason.ACCEPTED, "State Complete accepted")
_NO_ANSWER = Answer(False, Reason.COMMAND_NOT_ALLOWED, "")
_new_tuple = tuple.__new__


class Transition(NamedTuple):
    """One state or mode transition (``TransitionEvent``)."""

    time: float
    sequence: int
    from_state: State
    to_state: State
    from_mode: int
    to_mode: int
    trigger: Trigger
    command: int = 0
    source: str = ""
    skipped: tuple[State, ...] = ()
    detail: str = ""


# Enum members as module globals for the hot paths below: attribute access on an Enum class costs
# about 100 ns, a global about 20 ns, and these run on every transition.
_ACCEPTED, _NOT_ALLOWED = Reason.ACCEPTED, Reason.COMMAND_NOT_ALLOWED
_T_COMMAND, _T_INTERLOCK = Trigger.COMMAND, Trigger.INTERLOCK
_EXECUTE, _SUSPENDING, _SUSPENDED = S.EXECUTE, S.SUSPENDING, S.SUSPENDED
_UNSUSPEND = C.UNSUSPEND
_PRODUCTION = Mode.PRODUCTION
_OPERATOR = "operator"  # the default source of commands
#: Without EMs, every acting state completes at once except Execute (the run ends by command).
_COMPLETE_AT_ONCE = ACTING - {S.EXECUTE}


class StatusMark(NamedTuple):
    """Where a status publication was due; :meth:`Unit.drain` turns it into a StatusView."""

    time: float
    state: State
    sequence: int


# -- requests of one evaluation step -----------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class CommandRequest:
    cmd: int
    source: str = "operator"


@dataclass(frozen=True, slots=True)
class ModeRequest:
    mode: int | str
    source: str = "operator"


@dataclass(frozen=True, slots=True)
class CompleteReport:
    em: str
    state: int
    sequence: int


Request = CommandRequest | ModeRequest | CompleteReport


#: An accepted command: (final state, skipped, answer, command as int, its trigger).
_Accepted = tuple[State, tuple[State, ...], Answer, int, Trigger]
#: State Complete from an acting state: (final state, skipped, trigger, final state enabled).
_ScStep = tuple[State, tuple[State, ...], Trigger, bool]


class _Cmd(NamedTuple):
    """A command inside the engine, with what caused it."""

    cmd: int
    source: str
    trigger: Trigger = Trigger.COMMAND
    detail: str = ""
    alarm: AlarmEvent | None = None
    stop_id: int = 0


@dataclass(slots=True)
class Stats:
    """Counts for diagnostics."""

    commands_accepted: int = 0
    commands_rejected: int = 0
    stale_reports: int = 0
    sc_ignored: int = 0
    bad_reports: int = 0


@dataclass(slots=True)
class _Flags:
    mode_change_not_allowed_until: float = -math.inf
    interlocks: dict[str, tuple[str, int]] = field(default_factory=dict)  # key -> (reason, stop id)
    interlock_suspended: bool = False
    interlock_attempt: tuple[int, int] = (-1, -1)
    sc_refused: tuple[int, int] = (-1, -1)


def _priority(r: Request) -> int:
    if isinstance(r, CommandRequest):
        return PRIORITY.get(r.cmd, OTHER_COMMANDS)
    if isinstance(r, ModeRequest):
        return MODE_REQUESTS
    return STATE_COMPLETE_REPORTS


class Unit:
    """One PackML unit. ``Unit(config, clock)``; optionally a :class:`~.persistence.Store`.

    Inputs are methods (:meth:`command`, :meth:`set_mode`, :meth:`em_complete`, ...) answering
    with an :class:`~.reasons.Answer`; outputs are taken with :meth:`drain`; :meth:`advance` fires
    due deadlines and should be called periodically (the node does, every 50 ms).
    """

    # About 50 attributes: past 30, CPython gives up the compact per-instance dict and every
    # attribute access on the hot paths gets slower; slots keep them fast (bench/engine.py).
    __slots__ = (  # noqa: RUF023 (grouped by concern, not sorted)
        # state and mode
        "state", "mode", "mode_def", "sequence", "entered_at", "mode_requested",
        "mode_change_in_process", "_mode_source",
        # Command and Status tags
        "remote_enabled", "cntrl_cmd", "command_unit_mode", "mach_speed", "parameters", "products",
        "remote_commands", "stop_reason", "_stop_armed",
        # parts
        "config", "_clock", "store", "on_input", "restored", "flags", "stats", "times", "counters",
        "alarms", "equipment",
        # tables resolved at start
        "_resolved", "_accepted", "_sc_resolved", "_timed",
        # evaluation
        "_t", "_out", "_deadlines", "_next_due", "_deadline_counter", "_advance_to", "_internal",
        "_step_winner", "_restart_detail",
        # caches and publication
        "_valid_cache", "_missing_cache", "_rev", "_status_key", "_status_flush_due", "_admin_key",
        "_admin_flush_due", "_alarms_seen",
    )  # fmt: skip

    def __init__(self, config: UnitConfig, clock: Clock, store: Store | None = None) -> None:
        self.config = config
        self._clock = clock
        self.store = store
        #: Called with (time, input name, arguments) for every input: the replay log.
        self.on_input: Callable[[float, str, dict[str, Any]], None] | None = None
        now = float(clock())  # the clock returns seconds as a float
        self._t = now
        self.state = S.STOPPED
        self.mode = int(config.initial_mode)
        self.mode_def: ModeDef = config.modes[self.mode]
        self.sequence = 0
        self.entered_at = now
        self.mode_requested = self.mode
        self.mode_change_in_process = False
        self._mode_source = ""
        self.remote_enabled = config.remote_commands_enabled
        self.cntrl_cmd = 0
        self.command_unit_mode = self.mode
        self.mach_speed = config.mach_speed
        self.parameters: list[Descriptor] = list(config.parameters)
        self.products: list[Product] = list(config.products)
        self.remote_commands: dict[int, tuple[int, int]] = {}  # interface number -> (cmd, value)
        self.stop_reason: AlarmEvent | None = None
        self._stop_armed = True
        self.flags = _Flags()
        self.stats = Stats()
        self.times = ModeStateTimes(now, self.mode, self.state)
        self.counters = Counters(config.sizes.counters, dict(config.counters))
        self.alarms = AlarmManager(
            {(a.id, a.value): a for a in config.alarms},
            dict(config.reactions),
            config.sizes.alarms,
            config.sizes.warnings,
            config.sizes.history,
        )
        self.equipment = Equipment()
        for em_cfg in config.equipment_modules:
            em = self.equipment.add(em_cfg.name, configured=True, active=em_cfg.active)
            em.lost_reaction = em_cfg.lost_reaction
            em.ignore_loss = not self._lost_reaction(em)
        self._resolved = self._resolve_all()
        self._timed = frozenset(config.timeouts) | frozenset(config.min_dwell)
        #: The accepted entries of _resolved as mode -> [state] -> {command: (final state, skipped,
        #: answer, command as a plain int, trigger when an operator gave it)}: indexing by state and
        #: command is about twice as fast as hashing a (state, mode, command) key.
        self._accepted: dict[int, list[dict[int, _Accepted]]] = {
            mode: [{} for _ in range(NUM_STATES)] for mode in config.modes
        }
        for (state, mode, cmd), (reason, final, skipped, answer) in self._resolved.items():
            if reason is Reason.ACCEPTED and final is not None:
                trigger = Trigger.SKIP if skipped else Trigger.COMMAND
                self._accepted[mode][state][cmd] = (final, skipped, answer, int(cmd), trigger)
        self._sc_resolved = self._resolve_state_complete()
        self._out: list[tuple[str, Any]] = []
        self._deadlines: list[tuple[float, int, str, Any]] = []
        self._next_due = math.inf  # the earliest deadline's time (the heap's top), inf when none
        self._deadline_counter = 0
        self._advance_to = now  # the time _advance is bringing the unit to
        self._internal: list[_Cmd] = []
        self._valid_cache: dict[tuple[Any, ...], tuple[Cmd, ...]] = {}
        self._missing_cache: tuple[int, list[EquipmentModule]] = (-1, [])
        self._rev = 0  # +1 on status-relevant changes not covered by other version counters
        self._status_key: tuple[int, ...] = ()
        self._status_flush_due = False
        self._admin_key: tuple[int, ...] = ()
        self._admin_flush_due = False
        self._alarms_seen = -1
        self._step_winner: tuple[int, str] | None = None
        self._restart_detail = "unit started"
        self._restore(now)
        self._transition(S.STOPPED, Trigger.RESTART, source="unit", detail=self._restart_detail)
        self._status_key = self._key()  # the start-up status is the baseline for later changes
        if store is not None:
            self._every("save", config.persistence_period)
        self._every("admin", config.admin_period)

    def _resolve_all(
        self,
    ) -> dict[tuple[int, int, int], tuple[Reason, State | None, tuple[State, ...], Answer]]:
        """(state, mode, command) -> (reason, final state, skipped, answer if accepted): the static
        part of every check, from the transition table and each mode's disabled states."""
        table = self.config.table
        out: dict[tuple[int, int, int], tuple[Reason, State | None, tuple[State, ...], Answer]] = {}
        for mode, mdef in self.config.modes.items():
            for state in _STATES:
                for cmd in _CMDS:
                    first = table.target(state, cmd) if cmd else None
                    if first is None:
                        out[(state, mode, cmd)] = (Reason.COMMAND_NOT_ALLOWED, None, (), _NO_ANSWER)
                        continue
                    final, skipped = resolve(first, mdef.disabled, table.state_complete)
                    if final in mdef.disabled:
                        out[(state, mode, cmd)] = (
                            Reason.STATE_DISABLED,
                            final,
                            skipped,
                            _NO_ANSWER,
                        )
                        continue
                    msg = f"{cmd.name} accepted: {state.name} -> {final.name}"
                    out[(state, mode, cmd)] = (
                        Reason.ACCEPTED,
                        final,
                        skipped,
                        Answer(True, Reason.ACCEPTED, msg),
                    )
        return out

    def _resolve_state_complete(self) -> dict[int, list[_ScStep | None]]:
        """mode -> [acting state] -> State Complete's (final state, skipped, trigger, whether the
        final state is enabled in the mode); None for states State Complete does not leave."""
        table = self.config.table
        out: dict[int, list[_ScStep | None]] = {}
        for mode, mdef in self.config.modes.items():
            steps: list[_ScStep | None] = [None] * NUM_STATES
            for state, nxt in table.state_complete.items():
                final, skipped = resolve(nxt, mdef.disabled, table.state_complete)
                trigger = Trigger.SKIP if skipped else Trigger.STATE_COMPLETE
                steps[state] = (final, skipped, trigger, final not in mdef.disabled)
            out[mode] = steps
        return out

    # ================================================================================================
    # Inputs. Each advances to the clock first; ``on_input`` sees (time, name, arguments) for replay.
    # ================================================================================================
    def _enter(self) -> None:
        if not self._status_key:  # the baseline of what the status shows (see _flush_status)
            self._status_key = self._key()
        now = self._clock()
        if now >= self._next_due:
            self._advance(now)
        elif now > self._t:
            self._t = now

    def _record(self, name: str, args: dict[str, Any]) -> None:
        if self.on_input is not None:
            self.on_input(self._t, name, args)

    def _leave(self) -> None:
        self._settle()
        self._flush_status()

    def command(self, cmd: int, source: str = _OPERATOR) -> Answer:
        """A state command (``Command.CntrlCmd`` + ``CmdChangeRequest``)."""
        now = self._clock()
        if now >= self._next_due:
            if not self._status_key:
                self._status_key = self._key()
            self._advance(now)
        elif now > self._t:
            self._t = now
        source = source or _OPERATOR
        if self.on_input is not None:
            self.on_input(self._t, "command", {"cmd": cmd, "source": source})
        eq, flags = self.equipment, self.flags
        entry = self._accepted[self.mode][self.state].get(cmd)
        if (  # the fast path: the table alone decides (no guard can refuse, nothing remote)
            entry is not None
            and (
                cmd not in ALARM_GUARDED
                or not (eq.modules or self.alarms.current or flags.interlocks)
            )
            and not self.mode_change_in_process
            and (source is _OPERATOR or not source.startswith("remote"))
        ):
            final, skipped, answer, cmd, trigger = entry
            self.stats.commands_accepted += 1
            self.cntrl_cmd = cmd
            more = self._transition(final, trigger, cmd, source, skipped, "", None, True)
            if not (more or flags.interlocks or flags.interlock_suspended):
                # Nothing for _settle and nothing changed after the last transition, whose
                # status is published with it: that is the baseline, and stays so until the
                # next input begins (which takes the key then, see _flush_status).
                return answer
        else:
            if not self._status_key:
                self._status_key = self._key()
            self._step_winner = None  # (only a refusal reads it: not on the fast path)
            answer = self._apply_command(cmd, source, self.state, None, True)
        if (  # anything left for _settle? (the command followed immediate State Complete itself)
            self._internal
            or self.mode_change_in_process
            or (eq.aggregating and not eq.pending)
            or flags.interlocks
            or flags.interlock_suspended
        ):
            self._settle()
        if self._status_key or self.alarms.version != self._alarms_seen:
            self._flush_status()
        return answer

    def set_mode(self, mode: int | str, source: str = "operator") -> Answer:
        """A mode change (``Command.UnitMode`` + ``UnitModeChangeRequest``), by number or name."""
        self._enter()
        source = source or "operator"
        self._record("set_mode", {"mode": mode, "source": source})
        answer = self._apply_mode(ModeRequest(mode, source))
        self._leave()
        return answer

    def step(self, requests: Sequence[Request]) -> list[Answer]:
        """Several requests in one evaluation step, applied by priority: Abort > Stop > Hold >
        Suspend > other commands > mode changes > State Complete (PACKML.md section 2)."""
        self._enter()
        if self.on_input is not None:
            self.on_input(self._t, "step", {"requests": [request_to_dict(r) for r in requests]})
        start_state = self.state
        self._step_winner = None
        answers: list[Answer] = [Answer.ok("")] * len(requests)
        for i in sorted(range(len(requests)), key=lambda i: _priority(requests[i])):
            r = requests[i]
            if isinstance(r, CommandRequest):
                answers[i] = self._apply_command(int(r.cmd), r.source or "operator", start_state)
            elif isinstance(r, ModeRequest):
                answers[i] = self._apply_mode(r)
            else:
                answers[i] = self._apply_report(r.em, r.state, r.sequence)
        self._leave()
        return answers

    # -- equipment modules ------------------------------------------------------------------------------
    def em_complete(self, name: str, state: int, sequence: int) -> Answer:
        """State Complete from EM ``name`` for (``state``, ``sequence``)."""
        self._enter()
        if self.on_input is not None:
            self.on_input(
                self._t, "em_complete", {"name": name, "state": state, "sequence": sequence}
            )
        answer = self._apply_report(name, state, sequence)
        if answer.accepted and not self.equipment.pending:
            self._settle()  # the last report: State Complete (or the mode change) follows
        self._flush_status()
        return answer

    def em_seen(self, name: str) -> Answer:
        """The EM ``name`` is alive (first heartbeat, or back after being lost)."""
        self._enter()
        self._record("em_seen", {"name": name})
        em = self.equipment.get(name)
        if em is None:
            if not self.config.allow_registration:
                self._leave()
                return Answer.no(
                    Reason.EM_UNKNOWN,
                    f"EM {name!r} is not configured and {self.config.name} does not accept "
                    "registrations (allow_registration: false)",
                )
            em = self.equipment.add(name, configured=False)
            em.ignore_loss = not self._lost_reaction(em)
            self.alarms.log_event(f"EM {name} registered", self._t, source=f"em:{name}")
            self._log("info", f"EM {name} registered (active)")
        if not em.online:
            em.online = True
            self.equipment.changed_roster()
            self.alarms.clear(self.config.system_alarms.em_lost, em.index, self._t)
            self.equipment.require(name)
            self._log("info", f"EM {name} online at {state_name(self.state)} seq {self.sequence}")
        self._leave()
        return Answer.ok(f"EM {name} online")

    def em_lost(self, name: str, detail: str = "") -> Answer:
        """The EM ``name`` missed its lease (or left); the configured reaction applies."""
        self._enter()
        self._record("em_lost", {"name": name, "detail": detail})
        em = self.equipment.get(name)
        if em is None or not em.online:
            self._leave()
            return Answer.no(Reason.NOTHING_TO_DO, f"EM {name!r} is not online")
        em.online = False
        self.equipment.changed_roster()
        # Inactive EMs are ignored (PACKML.md 4): switched off for diagnosis, losing them is no fault.
        reaction = self._lost_reaction(em) if em.active else 0
        if self.state in EXCUSE_OFFLINE or not reaction:
            self.equipment.excuse(name)
        why = f" ({detail})" if detail else ""
        category = {C.ABORT: 0, C.STOP: 2}.get(Cmd(reaction), 5) if reaction else 9
        definition = AlarmDef(
            id=self.config.system_alarms.em_lost,
            value=em.index,
            message=f"EM {name} lost{why}",
            category=category,
            warning=not reaction,
            reaction=reaction,
            em=name,
        )
        self._raise(definition, source="unit", trigger=Trigger.EM_LOST)
        what = command_name(reaction) if reaction else "none"
        self._log("warn", f"EM {name} lost{why}: reaction {what}")
        self._leave()
        return Answer.ok(f"EM {name} lost; reaction {what}")

    def em_request(self, name: str, cmd: int) -> Answer:
        """EM ``name`` asks the unit for command ``cmd`` (0 withdraws a request: nothing to do)."""
        if not cmd:
            return Answer.ok("request withdrawn")
        em = self.equipment.get(name)
        if em is not None and not em.active:
            return Answer.no(Reason.EM_UNKNOWN, f"EM {name} is inactive; its requests are ignored")
        return self.command(cmd, f"em:{name}")

    def em_interlock(self, name: str, blocked: bool, starved: bool, material: int = 0) -> Answer:
        """EM ``name`` reports Blocked/Starved (``Status.EquipmentInterlock``) and material bits."""
        self._enter()
        self._record(
            "em_interlock",
            {"name": name, "blocked": blocked, "starved": starved, "material": material},
        )
        em = self.equipment.get(name)
        if em is None:
            self._leave()
            return Answer.no(Reason.EM_UNKNOWN, f"no EM {name!r} in {self.config.name}")
        em.blocked, em.starved, em.material_interlock = bool(blocked), bool(starved), int(material)
        self.equipment.version += 1
        key = f"em:{name}"
        if em.active and (blocked or starved):
            what = "blocked" if blocked else "starved"
            stop_id = STOP_ID_BLOCKED if blocked else STOP_ID_STARVED
            self.flags.interlocks[key] = (f"{name} {what}", stop_id)
        else:
            self.flags.interlocks.pop(key, None)
        self._rev += 1
        self._leave()
        return Answer.ok("interlock updated")

    def em_count(self, name: str, kind: str, index: int, increment: int) -> Answer:
        """EM ``name`` adds ``increment`` to counter ``index`` of ``kind``
        (``consumed`` / ``processed`` / ``defective``)."""
        self._enter()
        self._record(
            "em_count", {"name": name, "kind": kind, "index": index, "increment": increment}
        )
        problem = self.counters.add(kind, int(index), int(increment))
        if problem:
            self.stats.bad_reports += 1
            self._leave()
            return Answer.no(Reason.INVALID_ARGUMENT, f"count from {name} refused: {problem}")
        self._leave()
        return Answer.ok("counted")

    def set_em_active(self, name: str, active: bool, source: str = "operator") -> Answer:
        """Switch ModuleActive; only outside Production, and always logged."""
        self._enter()
        self._record("set_em_active", {"name": name, "active": active, "source": source})
        answer = self._set_em_active(name, bool(active), source)
        self._leave()
        return answer

    def _set_em_active(self, name: str, active: bool, source: str) -> Answer:
        em = self.equipment.get(name)
        word = "active" if active else "inactive"
        if em is None:
            known = ", ".join(self.equipment.modules) or "none"
            return Answer.no(
                Reason.EM_UNKNOWN, f"no EM {name!r} in {self.config.name} (EMs: {known})"
            )
        if self.mode == Mode.PRODUCTION:
            return Answer.no(
                Reason.EM_SWITCH_IN_PRODUCTION,
                f"EM {name} can be switched {word} only outside PRODUCTION (now PRODUCTION, "
                f"{state_name(self.state)}); change to MAINTENANCE first",
            )
        if em.active == active:
            return Answer.ok(f"EM {name} already {word}")
        em.active = active
        self.equipment.changed_roster()
        self.alarms.log_event(f"EM {name} switched {word} by {source}", self._t, source=source)
        self._log("info", f"EM {name} switched {word} by {source}")
        if active:
            self.equipment.require(name)
        else:
            self.equipment.excuse(name)
            self.flags.interlocks.pop(f"em:{name}", None)
            # An inactive EM is no longer missing: its "EM lost" alarm goes inactive (latched), so
            # Clear and Reset recover without it (PACKML.md 9).
            self.alarms.clear(self.config.system_alarms.em_lost, em.index, self._t)
        return Answer.ok(f"EM {name} {word}")

    # -- alarms ----------------------------------------------------------------------------------------
    def set_alarm(
        self,
        alarm_id: int,
        value: int = 0,
        active: bool = True,
        source: str = "operator",
        em: str = "",
        warning: bool | None = None,
        category: int = -1,
        message: str = "",
    ) -> Answer:
        """Raise or clear alarm (``alarm_id``, ``value``). Unconfigured alarms need a category and
        a message; ``warning``/``category``/``message`` override the configuration when given."""
        self._enter()
        self._record(
            "set_alarm",
            {"alarm_id": alarm_id, "value": value, "active": active, "source": source, "em": em,
             "warning": warning, "category": category, "message": message},
        )  # fmt: skip
        answer = self._set_alarm(
            int(alarm_id), int(value), bool(active), source, em, warning, int(category), message
        )
        self._leave()
        return answer

    def _set_alarm(
        self,
        alarm_id: int,
        value: int,
        active: bool,
        source: str,
        em: str,
        warning: bool | None,
        category: int,
        message: str,
    ) -> Answer:
        if not active:
            ev = self.alarms.clear(alarm_id, value, self._t)
            if ev is None:
                return Answer.no(Reason.NOTHING_TO_DO, f"alarm {alarm_id}/{value} is not active")
            return Answer.ok(f"alarm {ev.label()} cleared (latched until reset)")
        d = self.alarms.definition(alarm_id, value)
        if d is None:
            if category < 0 or not message:
                return Answer.no(
                    Reason.ALARM_UNKNOWN,
                    f"alarm {alarm_id}/{value} is not configured on {self.config.name}; "
                    "give its category (0..9) and a message",
                )
            d = AlarmDef(alarm_id, value, message, category, bool(warning), None, em)
        elif category >= 0 or message or warning is not None:
            d = AlarmDef(
                d.id,
                d.value,
                message or d.message,
                category if category >= 0 else d.category,
                d.warning if warning is None else warning,
                d.reaction,
                d.em or em,
            )
        if not 0 <= d.category <= 9:
            return Answer.no(Reason.INVALID_ARGUMENT, f"category {d.category} is outside 0..9")
        what = "warning" if d.warning else "alarm"
        if not self._raise(d, source=source, em=em, trigger=Trigger.ALARM):
            return Answer.no(Reason.NOTHING_TO_DO, f"{what} {alarm_id}/{value} is already active")
        reaction = self.alarms.reaction_of(d)
        act = f"; reaction {command_name(reaction)}" if reaction else ""
        return Answer.ok(f"{what} {alarm_id}/{value} raised{act}")

    def em_alarm(
        self,
        name: str,
        alarm_id: int,
        value: int,
        active: bool,
        warning: bool = False,
        category: int = -1,
        message: str = "",
    ) -> Answer:
        """An alarm raised or cleared by EM ``name``."""
        return self.set_alarm(
            alarm_id, value, active, f"em:{name}", name, warning or None, category, message
        )

    def ack_alarms(
        self, alarm_id: int | None = None, value: int = 0, source: str = "operator"
    ) -> Answer:
        """Acknowledge one alarm, or all with ``alarm_id=None``; AckDateTime is stamped once."""
        self._enter()
        self._record("ack_alarms", {"alarm_id": alarm_id, "value": value, "source": source})
        key = None if alarm_id is None else (int(alarm_id), int(value))
        if key is not None and key not in self.alarms.current:
            self._leave()
            return Answer.no(
                Reason.ALARM_UNKNOWN, f"alarm {key[0]}/{key[1]} is not in the alarm list"
            )
        n = self.alarms.acknowledge(key, self._t)
        self._leave()
        if not n:
            which = "every alarm is" if key is None else f"alarm {key[0]}/{key[1]} is"
            return Answer.no(Reason.NOTHING_TO_DO, f"{which} already acknowledged")
        return Answer.ok(f"{n} acknowledged")

    def reset_alarms(self, clear_first_out: bool = False, source: str = "operator") -> Answer:
        """Clear latched alarms that are no longer active (and optionally the first-outs)."""
        self._enter()
        self._record("reset_alarms", {"clear_first_out": clear_first_out, "source": source})
        n = self.alarms.reset()
        if clear_first_out:
            self.alarms.clear_first_out()
        still = self.alarms.active_count()
        self._leave()
        tail = f"; {still} still active" if still else ""
        return Answer.ok(f"{n} cleared{tail}")

    # -- times, counters, speed, parameters --------------------------------------------------------------
    def reset_times(self, all_times: bool = False, source: str = "operator") -> Answer:
        """Reset the current mode's times (and its states'), or every time with ``all_times``."""
        self._enter()
        self._record("reset_times", {"all_times": all_times, "source": source})
        if all_times:
            self.times.reset_all(self._t)
            msg = "all times reset"
        else:
            self.times.reset_current_mode(self._t)
            msg = f"times of {self.mode_def.name} reset"
        self.alarms.log_event(f"{msg} by {source}", self._t, source=source)
        self._save()
        self._leave()
        return Answer.ok(msg)

    def reset_counters(self, source: str = "operator") -> Answer:
        """``Count`` of every counter to 0; ``AccCount`` is never reset."""
        self._enter()
        self._record("reset_counters", {"source": source})
        self.counters.reset()
        self.alarms.log_event(f"counters reset by {source}", self._t, source=source)
        self._save()
        self._leave()
        return Answer.ok("counters reset (AccCount kept)")

    def set_mach_speed(self, speed: float, source: str = "operator") -> Answer:
        self._enter()
        self._record("set_mach_speed", {"speed": speed, "source": source})
        if not math.isfinite(speed) or speed < 0:
            self._leave()
            return Answer.no(
                Reason.INVALID_ARGUMENT, f"machine speed must be a finite number >= 0, not {speed}"
            )
        self.mach_speed = float(speed)
        self._rev += 1
        self._leave()
        return Answer.ok(f"MachSpeed {speed:g}")

    def set_parameters(self, parameters: Iterable[Descriptor], source: str = "operator") -> Answer:
        """Set ``Command.Parameter[#]`` entries, matched by ID (a new ID takes a free slot)."""
        params = list(parameters)
        self._enter()
        self._record(
            "set_parameters", {"parameters": [p.__dict__ for p in params], "source": source}
        )
        answer = self._merge(
            self.parameters, params, lambda p: p.id, self.config.sizes.parameters, "parameter"
        )
        self._leave()
        return answer

    def set_product(self, products: Iterable[Product], source: str = "operator") -> Answer:
        """Set ``Command.Product[#]`` entries, matched by ProductID."""
        items = list(products)
        self._enter()
        self._record(
            "set_product", {"products": [product_to_dict(p) for p in items], "source": source}
        )
        sizes = self.config.sizes
        for p in items:
            too_many = (
                len(p.process_variables) > sizes.process_variables
                or len(p.ingredients) > sizes.ingredients
            )
            if too_many:
                self._leave()
                return Answer.no(
                    Reason.INVALID_ARGUMENT,
                    f"product {p.product_id}: more entries than the arrays hold "
                    f"({sizes.process_variables} process variables, {sizes.ingredients} ingredients)",
                )
        answer = self._merge(
            self.products, items, lambda p: p.product_id, sizes.products, "product"
        )
        self._leave()
        return answer

    def _merge(self, target: list[Any], items: list[Any], key: Callable[[Any], int], capacity: int,
               what: str) -> Answer:  # fmt: skip
        index = {key(x): i for i, x in enumerate(target)}
        new = {key(x) for x in items} - set(index)
        if len(target) + len(new) > capacity:
            return Answer.no(
                Reason.INVALID_ARGUMENT,
                f"{len(target) + len(new)} {what}s would not fit; the array holds {capacity}",
            )
        for x in items:
            if key(x) in index:
                target[index[key(x)]] = x
            else:
                index[key(x)] = len(target)
                target.append(x)
        self._rev += 1
        return Answer.ok(f"{len(items)} {what}(s) set")

    def set_remote_enabled(self, enabled: bool) -> None:
        """Whether commands with a ``remote...`` source are accepted."""
        self._enter()
        self._record("set_remote_enabled", {"enabled": enabled})
        self.remote_enabled = bool(enabled)
        self._rev += 1
        self._leave()

    def shutdown(self, detail: str = "") -> Answer:
        """The unit's own process is shutting down (Ctrl-C, SIGTERM): recorded as what it is, an
        event in the alarm history and, when the unit was producing (Execute or on its way
        there), its StopReason, so the restarted unit tells why it stopped. The state is not
        changed; status, alarms and admin go out at once (the process ends after this)."""
        self._enter()
        self._record("shutdown", {"detail": detail})
        message = f"unit shut down{f' ({detail})' if detail else ''} in {state_name(self.state)}"
        self.alarms.log_event(message, self._t, source="unit")
        if self._stop_armed and SETTLE.get(self.state) is S.EXECUTE:
            self.stop_reason = AlarmEvent(STOP_ID_SHUTDOWN, 0, message, 9, Kind.EVENT, self._t,
                                          source="unit", trigger=False, latched=False)  # fmt: skip
            self._stop_armed = False
            self._rev += 1
        self._capture_status()
        self._admin_key = self._admin_state()
        self._out.append(("admin", build_admin(self, self._t)))
        self._leave()
        return Answer.ok(message)

    def set_interlock(self, active: bool, reason: str = "", source: str = "remote") -> Answer:
        """A line interlock from outside (the coordinator): suspend while set, unsuspend when
        cleared (``interlock_reaction: suspend``)."""
        self._enter()
        self._record("set_interlock", {"active": active, "reason": reason, "source": source})
        key = f"ext:{source}"
        if active:
            stop_id = STOP_ID_STARVED if "starv" in reason.lower() else STOP_ID_BLOCKED
            self.flags.interlocks[key] = (reason or f"interlock from {source}", stop_id)
        else:
            self.flags.interlocks.pop(key, None)
        self._rev += 1
        self._leave()
        return Answer.ok(f"interlock {'set' if active else 'cleared'}")

    def advance(self) -> None:
        """Fire every deadline due by the clock's time (call periodically)."""
        self._enter()
        self._leave()

    def next_deadline(self) -> float | None:
        """When the engine has something to do next on its own (a timeout, a periodic admin...)."""
        return None if self._next_due == math.inf else self._next_due

    def fire_next(self, until: float) -> bool:
        """Fire the earliest deadline if it is due by ``until``; False when none is. Driving the
        engine one deadline at a time (and publishing after each) is what makes a live node and a
        replay produce the same messages (see packml_ros2.driver)."""
        if until < self._next_due:
            return False
        if not self._status_key:
            self._status_key = self._key()
        self._advance_to = until
        kind, data = self._pop_deadline()
        self._handlers()[kind](data)
        self._settle()
        self._flush_status()
        return True

    def apply_input(self, name: str, args: dict[str, Any]) -> Answer | None:
        """Apply a logged input (``on_input``'s name and arguments) again: the replay entry."""
        if name not in INPUTS:
            raise ValueError(
                f"{name!r} is not an engine input (inputs: {', '.join(sorted(INPUTS))})"
            )
        args = dict(args)
        if name == "step":
            return self.step([request_from_dict(r) for r in args["requests"]])  # type: ignore[return-value]
        if name == "set_parameters":
            args["parameters"] = [Descriptor(**d) for d in args["parameters"]]
        elif name == "set_product":
            args["products"] = [product_from_dict(p) for p in args["products"]]
        result: Answer | None = getattr(self, name)(**args)
        return result

    # ================================================================================================
    # Outputs and views
    # ================================================================================================
    def drain(self) -> list[tuple[str, Any]]:
        """Outputs since the last call, in order: ("transition", Transition), ("status",
        StatusMark), ("alarms", version), ("admin", AdminView), ("log", (level, text)).

        A status is due after every transition (publish :meth:`status_at` of the transition
        record) and at every ("status", mark) — changes that were not transitions. Marks and
        records are cheap; building the StatusView is left to the publisher."""
        out, self._out = self._out, []
        return out

    def status_at(self, mark: StatusMark | Transition) -> StatusView:
        """The status at a drained transition or mark: its state, sequence and time, the other
        fields as they are now."""
        if isinstance(mark, Transition):
            mark = StatusMark(mark.time, mark.to_state, mark.sequence)
        return build_status(self, mark)

    @property
    def now(self) -> float:
        return self._t

    def status(self) -> StatusView:
        return build_status(self, StatusMark(self._t, self.state, self.sequence))

    def admin(self, at: float | None = None) -> AdminView:
        return build_admin(self, self._t if at is None else at)

    def valid_commands(self, state: State | None = None) -> tuple[Cmd, ...]:
        """Commands an operator could issue now (cached per state, mode and constraints)."""
        state = self.state if state is None else state
        key = (
            state,
            self.mode,
            self.alarms.blocking_version,
            self.equipment.roster_version,
            bool(self.flags.interlocks),
            self.mode_change_in_process,
        )
        cached = self._valid_cache.get(key)
        if cached is None:
            saved, self.state = self.state, state
            try:
                cached = tuple(
                    c for c in _CMDS if c and self._check(c, "operator")[0] is Reason.ACCEPTED
                )
            finally:
                self.state = saved
            if len(self._valid_cache) > 4096:
                self._valid_cache.clear()
            self._valid_cache[key] = cached
        return cached

    def state_requested(self, state: State | None = None) -> State:
        state = self.state if state is None else state
        return SETTLE.get(state, state)

    @property
    def interlock_active(self) -> bool:
        return bool(self.flags.interlocks)

    @property
    def mode_change_not_allowed(self) -> bool:
        return self._t < self.flags.mode_change_not_allowed_until

    def missing_ems(self) -> list[EquipmentModule]:
        """Active EMs that are offline and whose loss is not ignored."""
        version, cached = self._missing_cache
        if version != self.equipment.roster_version:
            cached = [em for em in self.equipment.missing() if self._lost_reaction(em)]
            self._missing_cache = (self.equipment.roster_version, cached)
        return cached

    # ================================================================================================
    # The state machine
    # ================================================================================================
    def _check(self, cmd: int, source: str) -> tuple[Reason, State | None, tuple[State, ...], str]:
        """Whether ``cmd`` from ``source`` is valid now: (reason, final state, skipped, detail)."""
        if not 1 <= cmd <= 10:
            return Reason.UNKNOWN_COMMAND, None, (), ""
        if not self.remote_enabled and source.startswith("remote"):
            return Reason.REMOTE_DISABLED, None, (), ""
        if self.mode_change_in_process and cmd not in FAULT_COMMANDS:
            return Reason.MODE_CHANGE_IN_PROCESS, None, (), ""
        reason, final, skipped, _ = self._resolved[(self.state, self.mode, cmd)]
        if reason is not _ACCEPTED or cmd not in ALARM_GUARDED:
            return reason, final, skipped, ""
        if cmd in MOTION:
            missing = self.missing_ems()
            if missing:
                return Reason.EM_MISSING, final, skipped, ", ".join(em.name for em in missing)
        if self.alarms.current:
            blocker = self.alarms.blocking(cmd)
            if blocker is not None:
                detail = f"alarm {blocker.label()} with reaction {command_name(blocker.reaction)}"
                return Reason.ALARM_ACTIVE, final, skipped, detail
        if cmd == _UNSUSPEND and self.flags.interlocks and self.config.interlock_reaction:
            detail = "; ".join(r for r, _ in self.flags.interlocks.values())
            return Reason.INTERLOCK_ACTIVE, final, skipped, detail
        return _ACCEPTED, final, skipped, ""

    def _refusal(
        self, cmd: int, source: str, reason: Reason, final: State | None, detail: str
    ) -> str:
        name = command_name(cmd)
        valid = names_of(self.valid_commands()) or "none"
        where = f"{state_name(self.state)} in {self.mode_def.name} mode"
        if reason is Reason.UNKNOWN_COMMAND:
            text = (
                f"command {cmd} is not a PackML command (1..10: {names_of(range(1, 11))}); "
                f"now {where}"
            )
        elif reason is Reason.REMOTE_DISABLED:
            text = (
                f"{name} from {source} refused: remote commands are disabled on {self.config.name} "
                f"(parameter remote_commands_enabled); now {where}"
            )
        elif reason is Reason.MODE_CHANGE_IN_PROCESS:
            waiting = ", ".join(sorted(self.equipment.pending)) or "none"
            text = (
                f"{name} refused in {where}: mode change {self.mode_def.name} -> "
                f"{self._mode_name(self.mode_requested)} in process (waiting for EMs: {waiting})"
            )
        elif reason is Reason.STATE_DISABLED:
            target = state_name(final) if final is not None else "its target"
            text = f"{name} not allowed in {where}: {target} is disabled in {self.mode_def.name}"
        elif reason is Reason.EM_MISSING:
            text = (
                f"{name} refused in {where}: active EM {detail} offline; bring it back or switch "
                "it inactive outside PRODUCTION"
            )
        elif reason is Reason.ALARM_ACTIVE:
            text = f"{name} refused in {where}: {detail} is still active"
        elif reason is Reason.INTERLOCK_ACTIVE:
            text = f"{name} refused in {where}: interlock still active ({detail})"
        else:
            text = f"{name} not allowed in {where}"
        return f"{text} (valid now: {valid})"

    def _apply_command(
        self,
        cmd: int,
        source: str,
        start_state: State,
        cause: _Cmd | None = None,
        follow: bool = False,
    ) -> Answer:
        """Validate and apply one command; ``cause`` carries what raised an internal one.
        ``follow``: the command is alone in its step, so State Complete that is immediate follows
        at once (see :meth:`_transition`). (:meth:`command` has the fast path.)"""
        cmd = int(cmd)
        reason, final_or_none, skipped, detail = self._check(cmd, source)
        if reason is not _ACCEPTED or final_or_none is None:
            return self._reject(cmd, source, start_state, cause, reason, final_or_none, detail)
        final, skipped, answer, cmd, trigger = self._accepted[self.mode][self.state][cmd]
        if self.mode_change_in_process:  # only Abort and Stop pass _check then
            self._abandon_mode_change(f"{command_name(cmd)} from {source}")
        self.stats.commands_accepted += 1
        self.cntrl_cmd = cmd
        if source.startswith("remote"):
            self._note_remote(cmd, source)
        if cause is None:
            detail = ""
        else:
            if cause.trigger is not _T_COMMAND:
                trigger = cause.trigger
            detail = cause.detail
        self._step_winner = (cmd, source)
        self._transition(final, trigger, cmd, source, skipped, detail, cause, follow)
        return answer

    def _reject(self, cmd: int, source: str, start_state: State, cause: _Cmd | None, reason: Reason,
                final: State | None, detail: str) -> Answer:  # fmt: skip
        self.stats.commands_rejected += 1
        winner = self._step_winner
        was_valid = self._resolved.get((start_state, self.mode, cmd), (None,))[0] is _ACCEPTED
        if winner is not None and reason is _NOT_ALLOWED and was_valid:
            return Answer.no(
                Reason.SUPERSEDED,
                f"{command_name(cmd)} superseded by {command_name(winner[0])} from {winner[1]} in the "
                f"same step (now {state_name(self.state)})",
            )
        msg = self._refusal(cmd, source, reason, final, detail)
        if cause is not None or source.startswith("em:"):
            self._log("info", f"{source}: {msg}")
        return Answer.no(reason, msg)

    def _note_remote(self, cmd: int, source: str) -> None:
        """Record a remote command in ``Command.RemoteInterface[#]`` of its sender, if configured."""
        sender = source.partition(":")[2]
        for ri in self.config.remote_interfaces:
            if ri.name and ri.name == sender:
                self.remote_commands[ri.number] = (cmd, 1)
                self._rev += 1

    def _apply_report(self, name: str, state: int, sequence: int) -> Answer:
        eq = self.equipment
        if eq.report(name, state, sequence):
            return _REPORT_OK
        if name not in eq.modules:
            self.stats.bad_reports += 1
            return Answer.no(Reason.EM_UNKNOWN, f"State Complete from unknown EM {name!r}")
        self.stats.stale_reports += 1
        return Answer.no(
            Reason.NOTHING_TO_DO,
            f"stale State Complete from {name} for {state_name(state)} seq {sequence} "
            f"(now {state_name(self.state)} seq {self.sequence})",
        )

    def _transition(
        self,
        to: State,
        trigger: Trigger,
        cmd: int = 0,
        source: str = "",
        skipped: tuple[State, ...] = (),
        detail: str = "",
        cause: _Cmd | None = None,
        follow: bool = False,
    ) -> bool:
        """Enter ``to``. With ``follow``, then take State Complete as long as it is immediate
        (nothing to wait for: no EM owes it, no dwell, nothing queued, no mode change): exactly
        what :meth:`_settle` would do next, in one loop. Only for a request alone in its step:
        in a :meth:`step`, the other requests are judged in the state the first one reached.

        Returns, with ``follow``, whether :meth:`_settle` may have something left (a queued
        command, a mode change, a State Complete it must refuse); False when the unit stopped in
        a state that waits (interlocks aside, which the caller checks)."""
        t = self._t
        mode = self.mode
        times = self.times
        emit = self._out.append
        eq = self.equipment
        flags = self.flags
        alarms = self.alarms
        timed = self._timed
        sc_steps = self._sc_resolved[mode]
        state_current = times.state_current
        base = mode * NUM_STATES
        while True:
            frm = self.state
            self.sequence = seq = self.sequence + 1
            self.state = to
            self.entered_at = t
            if skipped or trigger is _T_INTERLOCK or flags.interlock_suspended:
                self._entry_actions(to, skipped, trigger, cmd, source, cause)
            elif to in ENTRY_FLAGS:
                if to in _REARMING and not alarms.current and not alarms.first_out_by_category:
                    self._stop_armed = True  # all _entry_actions would do: nothing to reset
                else:
                    self._entry_actions(to, skipped, trigger, cmd, source, cause)
            # ModeStateTimes.enter(t, mode, to, planned) for a transition within a mode, inlined:
            # the call costs 13 % of a transition (bench/engine_instructions.py). Time has passed
            # only before the first of a command's transitions.
            if t > times._since:
                times._close(t)
            state_current[base + to] = 0.0
            times._state = to
            times._planned = self.stop_reason is not None and self._planned()  # OEE planned stops
            emit(
                (
                    "transition",
                    _new_tuple(
                        Transition,
                        (t, seq, frm, to, mode, mode, trigger, cmd, source, skipped, detail),
                    ),
                )
            )
            if not eq.modules:  # Equipment.begin, inlined for units without EMs
                eq.state, eq.sequence = to, seq
                eq.aggregating = aggregating = to in _COMPLETE_AT_ONCE
            else:
                if to is _EXECUTE:
                    eq.begin(to, seq, eq.active_count() > 0, False)
                else:
                    eq.begin(to, seq, to in ACTING, to in EXCUSE_OFFLINE)
                aggregating = eq.aggregating and not eq.pending
            if timed and to in timed:  # (an empty set is cheaper to test than to search)
                config = self.config
                if to in config.timeouts:
                    self._at(t + config.timeouts[to], "timeout", (to, seq))
                if to in config.min_dwell:
                    self._at(t + config.min_dwell[to], "dwell", (to, seq))
                    aggregating = False  # State Complete waits for the dwell (_settle)
            alarms_version = alarms.version
            if alarms_version != self._alarms_seen:
                self._alarms_seen = alarms_version
                emit(("alarms", alarms_version))
            if self.store is not None:
                self._save()
            # State Complete, at once? (the order of _settle: queued commands, mode change, SC)
            if not (follow and aggregating):
                more = False
                break
            if self._internal or self.mode_change_in_process:
                more = True
                break
            to, skipped, trigger, enabled = sc_steps[to]  # type: ignore[misc]  # acting: not None
            if not enabled:
                more = True  # _settle refuses it (and says so)
                break
            cmd, source, detail, cause = 0, "unit", "", None
        # A status is published after every transition (never coalesced); the key of what it
        # shows is taken when the input is done (_flush_status).
        self._status_key = ()
        return more

    def _entry_actions(self, to: State, skipped: tuple[State, ...], trigger: Trigger, cmd: int,
                       source: str, cause: _Cmd | None) -> None:  # fmt: skip
        """Alarm reset on Resetting/Clearing, first-out clear on Starting, the StopReason, the
        interlock flag; skipped (disabled) states count as entered."""
        for s in (*skipped, to) if skipped else (to,):
            flags = ENTRY_FLAGS.get(s, 0)
            if not flags:
                continue
            alarms = self.alarms
            if flags & _RESET_ALARMS and alarms.current:
                alarms.reset()
            if flags & _CLEAR_FIRST_OUT and alarms.first_out_by_category:
                alarms.clear_first_out()
            if flags & _REARM:
                self._stop_armed = True
            elif flags & _STOP and self._stop_armed:
                self.stop_reason = self._stop_reason_of(cause or _Cmd(cmd, source, trigger))
                self._stop_armed = False
        if self.flags.interlock_suspended or trigger is _T_INTERLOCK:
            if trigger is _T_INTERLOCK and (to is _SUSPENDING or _SUSPENDING in skipped):
                self.flags.interlock_suspended = True
            elif to is not _SUSPENDING and to is not _SUSPENDED:
                self.flags.interlock_suspended = False

    def _stop_reason_of(self, cause: _Cmd) -> AlarmEvent:
        if cause.alarm is not None:
            return cause.alarm
        t = self._t
        if cause.trigger is Trigger.INTERLOCK:
            return AlarmEvent(
                cause.stop_id or STOP_ID_BLOCKED, cause.cmd, cause.detail or "interlock", 0,
                Kind.EVENT, t, source=cause.source, reaction=cause.cmd, trigger=False, latched=False,
            )  # fmt: skip
        stop_id = STOP_ID_REMOTE if cause.source.startswith("remote") else STOP_ID_OPERATOR
        return AlarmEvent(
            stop_id, cause.cmd, f"{command_name(cause.cmd)} by {cause.source}", 0, Kind.COMMAND, t,
            source=cause.source, reaction=cause.cmd, trigger=False, latched=False,
        )  # fmt: skip

    def _planned(self) -> bool:
        """Whether the unit is in a planned stop now (OEE): Production, stopped, and the stop
        reason is in ``planned_stop_ids`` (OMAC "out of service" 4000..4999 by default)."""
        if (
            self.stop_reason is None
            or self.mode != _PRODUCTION
            or self.state not in PLANNED_STOP_STATES
        ):
            return False
        lo, hi = self.config.planned_stop_ids
        return lo <= self.stop_reason.id <= hi

    def _sc_ready(self) -> bool:
        """Every EM that must report has (the caller checked); dwell and refusal remain."""
        if self.flags.sc_refused[1] == self.sequence:
            return False
        min_dwell = self.config.min_dwell
        if min_dwell and self.state in min_dwell:
            return self._t >= self.entered_at + min_dwell[self.state]
        return True

    def _refuse_state_complete(self, final: State) -> None:
        """State Complete would lead into a state disabled in this mode: ignore it (counted)."""
        self.stats.sc_ignored += 1
        self.flags.sc_refused = (self.state, self.sequence)
        self._log(
            "info",
            f"State Complete of {state_name(self.state)} ignored: {state_name(final)} is disabled "
            f"in {self.mode_def.name}",
        )

    def _settle(self) -> None:
        """Apply what follows from the current situation until nothing more does: queued internal
        commands (alarm reactions, EM loss, interlocks) by priority, then State Complete."""
        eq = self.equipment
        flags = self.flags
        for _ in range(1000):
            if self._internal:
                queue = sorted(self._internal, key=lambda r: PRIORITY.get(r.cmd, OTHER_COMMANDS))
                self._internal = []
                start = self.state
                self._step_winner = None
                for r in queue:
                    self._apply_command(r.cmd, r.source, start, r)
                continue
            if self.mode_change_in_process:
                if not eq.pending or not eq.aggregating:
                    self._finish_mode_change()
                    continue
                return
            if (
                eq.aggregating
                and not eq.pending
                and (
                    (not self.config.min_dwell and flags.sc_refused[1] != self.sequence)
                    or self._sc_ready()
                )
            ):
                step = self._sc_resolved[self.mode][self.state]
                assert step is not None  # aggregating: an acting state
                final, skipped, trigger, enabled = step
                if enabled:
                    self._transition(final, trigger, 0, "unit", skipped, "", None, True)
                    continue
                self._refuse_state_complete(final)
            if (flags.interlocks or flags.interlock_suspended) and self._interlock_action():
                continue
            return

    def _interlock_action(self) -> bool:
        if not self.config.interlock_reaction:
            return False
        key = (self.state, self.sequence)
        if self.flags.interlock_attempt == key:
            return False
        if self.flags.interlocks and self.state is S.EXECUTE:
            reason, stop_id = next(iter(self.flags.interlocks.values()))
            self.flags.interlock_attempt = key
            self._internal.append(
                _Cmd(C.SUSPEND, "interlock", Trigger.INTERLOCK, reason, stop_id=stop_id)
            )
            return True
        if (
            not self.flags.interlocks
            and self.flags.interlock_suspended
            and self.state is S.SUSPENDED
        ):
            self.flags.interlock_attempt = key
            self._internal.append(
                _Cmd(C.UNSUSPEND, "interlock", Trigger.INTERLOCK, "interlock cleared")
            )
            return True
        return False

    # -- modes ---------------------------------------------------------------------------------------------
    def _mode_name(self, number: int) -> str:
        m = self.config.modes.get(number)
        return m.name if m else f"MODE_{number}"

    def _apply_mode(self, r: ModeRequest) -> Answer:
        target = self._find_mode(r.mode)
        if target is None:
            configured = ", ".join(f"{n} {m.name}" for n, m in sorted(self.config.modes.items()))
            return Answer.no(
                Reason.MODE_UNKNOWN,
                f"mode {r.mode!r} is not configured on {self.config.name} (now {state_name(self.state)} "
                f"in {self.mode_def.name} mode; configured: {configured})",
            )
        if r.source.startswith("remote") and not self.remote_enabled:
            return Answer.no(
                Reason.REMOTE_DISABLED,
                f"mode change to {target.name} from {r.source} refused: remote commands are "
                f"disabled on {self.config.name}",
            )
        if self.mode_change_in_process:
            return Answer.no(
                Reason.MODE_CHANGE_IN_PROCESS,
                f"mode change to {target.name} refused: change to "
                f"{self._mode_name(self.mode_requested)} still in process",
            )
        if target.number == self.mode:
            return Answer.ok(f"already in {target.name}")
        why = mode_change_refusal(self.mode_def, target, self.state)
        if why is not None:
            self.flags.mode_change_not_allowed_until = self._t + MODE_CHANGE_NOT_ALLOWED_SECONDS
            self._at(self.flags.mode_change_not_allowed_until, "lamp_off", None)
            self._rev += 1
            self._capture_status()
            return Answer.no(
                Reason.MODE_CHANGE_NOT_ALLOWED,
                f"mode change {self.mode_def.name} -> {target.name} not allowed in "
                f"{state_name(self.state)}: {why}",
            )
        self.command_unit_mode = target.number
        self.mode_requested = target.number
        self.mode_change_in_process = True
        self._mode_source = r.source
        self.sequence += 1
        self.equipment.begin(
            self.state, self.sequence, self.equipment.active_count() > 0, excuse_offline=True
        )
        self._at(self._t + self.config.mode_change_timeout, "mode_timeout", self.sequence)
        self._capture_status()
        return Answer.ok(f"mode change {self.mode_def.name} -> {target.name} accepted")

    def _abandon_mode_change(self, why: str) -> None:
        """A fault command arrived while a mode change was in process: the mode stays."""
        target = self.mode_requested
        self.mode_requested = self.mode
        self.mode_change_in_process = False
        self._rev += 1
        self._log(
            "warn",
            f"mode change {self.mode_def.name} -> {self._mode_name(target)} abandoned: {why}",
        )

    def _find_mode(self, mode: int | str) -> ModeDef | None:
        if isinstance(mode, str) and not mode.strip().isdigit():
            return self.config.mode_by_name(mode)
        return self.config.modes.get(int(mode))

    def _finish_mode_change(self) -> None:
        frm = self.mode
        self.mode = self.mode_requested
        self.mode_def = self.config.modes[self.mode]
        self.mode_change_in_process = False
        self.times.enter(self._t, self.mode, self.state, self._planned())
        self.equipment.begin(self.state, self.sequence, False, excuse_offline=True)
        self._out.append(
            (
                "transition",
                Transition(self._t, self.sequence, self.state, self.state, frm, self.mode, Trigger.MODE,
                           0, self._mode_source, (), f"{self._mode_name(frm)} -> {self.mode_def.name}"),
            )
        )  # fmt: skip
        self._log(
            "info", f"mode {self._mode_name(frm)} -> {self.mode_def.name} ({self._mode_source})"
        )
        self._status_key = ()  # a status is published after the transition record
        self._save()

    # -- alarms inside -------------------------------------------------------------------------------------
    def _raise(
        self, d: AlarmDef, source: str, em: str = "", trigger: Trigger = Trigger.ALARM
    ) -> bool:
        """Raise ``d``; on a rising edge its reaction is queued. False when it was active already."""
        raised = self.alarms.raise_(d, self._t, source=source, em=em)
        if raised.rising and raised.reaction:
            self._internal.append(
                _Cmd(
                    raised.reaction,
                    f"alarm:{d.id}",
                    trigger,
                    raised.event.message,
                    alarm=raised.event,
                )
            )
        return raised.rising

    def _lost_reaction(self, em: EquipmentModule) -> int:
        return self.config.em_lost_reaction if em.lost_reaction is None else em.lost_reaction

    # -- deadlines ----------------------------------------------------------------------------------------
    def _at(self, when: float, kind: str, data: Any) -> None:
        self._deadline_counter += 1
        heapq.heappush(self._deadlines, (when, self._deadline_counter, kind, data))
        self._next_due = self._deadlines[0][0]

    def _pop_deadline(self) -> tuple[str, Any]:
        """Take the earliest deadline and bring the unit's time to it: (kind, data)."""
        when, _, kind, data = heapq.heappop(self._deadlines)
        self._next_due = self._deadlines[0][0] if self._deadlines else math.inf
        self._t = max(self._t, when)
        return kind, data

    def _every(self, kind: str, period: float) -> None:
        when = self._t + period
        behind = self._advance_to - when
        if behind > MAX_CATCH_UP * period:  # the clock jumped: do not replay every missed period
            when += period * math.floor(behind / period)
        self._at(when, kind, period)

    def _handlers(self) -> dict[str, Callable[[Any], None]]:
        return {
            "timeout": self._on_timeout,
            "dwell": self._on_dwell,
            "mode_timeout": self._on_mode_timeout,
            "status": self._on_status,
            "lamp_off": self._on_lamp_off,
            "admin_change": self._on_admin_change,
            "save": self._on_save,
            "admin": self._on_admin,
        }

    def _advance(self, now: float) -> None:
        handlers = self._handlers()
        self._advance_to = now
        while now >= self._next_due:
            kind, data = self._pop_deadline()
            handlers[kind](data)
            self._settle()
            self._flush_status()
        self._t = max(self._t, now)

    def _on_timeout(self, data: tuple[State, int]) -> None:
        state, seq = data
        if (self.state, self.sequence) != (state, seq):
            return
        missing = sorted(self.equipment.pending) or ["minimum dwell"]
        sa = self.config.system_alarms
        d = AlarmDef(
            sa.state_timeout,
            int(state),
            f"{state_name(state)} timed out waiting for {', '.join(missing)}",
            sa.state_timeout_category,
        )
        self._raise(d, source="unit", trigger=Trigger.TIMEOUT)
        self.alarms.clear(d.id, d.value, self._t)

    def _on_dwell(self, data: tuple[State, int]) -> None:
        """Nothing to do here: :meth:`_settle`, run after every deadline, completes the state."""

    def _on_mode_timeout(self, seq: int) -> None:
        if not self.mode_change_in_process or self.sequence != seq:
            return
        waiting = ", ".join(sorted(self.equipment.pending))
        target = self.mode_requested
        self.mode_requested = self.mode
        self.mode_change_in_process = False
        self.equipment.begin(self.state, self.sequence, False, excuse_offline=True)
        sa = self.config.system_alarms
        d = AlarmDef(
            sa.mode_change_timeout,
            target,
            f"mode change to {self._mode_name(target)} timed out waiting for {waiting}",
            sa.mode_change_timeout_category,
        )
        self._raise(d, source="unit", trigger=Trigger.TIMEOUT)
        self.alarms.clear(d.id, d.value, self._t)
        self._rev += 1
        self._capture_status()

    def _on_lamp_off(self, _: Any) -> None:
        """``mode_change_not_allowed`` went out (3 s after the refusal): publish that."""
        if not self.mode_change_not_allowed:
            self._rev += 1
            self._capture_status()

    def _on_status(self, _: Any) -> None:
        self._status_flush_due = False
        if self._key() != self._status_key:
            self._capture_status()

    def _on_admin_change(self, _: Any) -> None:
        self._admin_flush_due = False
        self._admin_key = self._admin_state()
        self._out.append(("admin", build_admin(self, self._t)))

    def _admin_state(self) -> tuple[int, ...]:
        return (self.sequence, self.counters.version, self.alarms.version, self._rev)

    def _on_save(self, period: float) -> None:
        self._save()
        self._every("save", period)

    def _on_admin(self, period: float) -> None:
        self._admin_key = self._admin_state()
        self._out.append(("admin", build_admin(self, self._t)))
        self._every("admin", period)

    # -- status publication ---------------------------------------------------------------------------
    def _key(self) -> tuple[int, ...]:
        return (self.sequence, self._rev, self.equipment.version, self.alarms.version)

    def _capture_status(self) -> None:
        """A transition or mode event: publish the status now."""
        self._status_key = (self.sequence, self._rev, self.equipment.version, self.alarms.version)
        self._out.append(("status", StatusMark(self._t, self.state, self.sequence)))
        if self.alarms.version != self._alarms_seen:
            self._alarms_seen = self.alarms.version
            self._out.append(("alarms", self.alarms.version))

    def _flush_status(self) -> None:
        """Other changes (EM progress, alarms, speed...) are published at most every 50 ms.

        ``_status_key`` is what the last published status showed; ``()`` after a transition (its
        status is published with it) until the input ends, or, after a command's fast path, until
        the next input begins: the key taken then is the baseline, since nothing changes between
        inputs."""
        if not self._status_key:  # a transition published the status: that is the new baseline
            self._status_key = self._key()
        elif not self._status_flush_due and self._key() != self._status_key:
            self._status_flush_due = True
            self._at(self._t + STATUS_COALESCE, "status", None)
        if self.alarms.version != self._alarms_seen:
            self._alarms_seen = self.alarms.version
            self._out.append(("alarms", self.alarms.version))
        if not self._admin_flush_due and self._admin_state() != self._admin_key:
            self._admin_flush_due = True
            self._at(self._t + ADMIN_COALESCE, "admin_change", None)

    def _log(self, level: str, text: str) -> None:
        self._out.append(("log", (level, text)))

    # -- persistence -----------------------------------------------------------------------------------
    def document(self) -> dict[str, Any]:
        """What persistence stores: everything of the admin data, never the state."""
        return {
            "sequence": self.sequence,
            "times": self.times.to_dict(self._t),
            "counters": self.counters.to_dict(),
            "alarms": self.alarms.to_dict(),
            "stop_reason": self.stop_reason.to_dict() if self.stop_reason else None,
            "mach_speed": self.mach_speed,
            "saved_at": self._t,
        }

    def _save(self) -> None:
        if self.store is not None:
            self.store.save(self.document(), self._t)

    def _restore(self, now: float) -> None:
        data = self.store.load() if self.store is not None else None
        self.restored: dict[str, Any] | None = data
        if data is None:
            return
        self.sequence = int(data.get("sequence", 0))
        self.times.restore(data.get("times", {}), now)
        self.counters.restore(data.get("counters", {}))
        self.alarms.restore(data.get("alarms", {}))
        if data.get("stop_reason"):
            self.stop_reason = AlarmEvent.from_dict(data["stop_reason"])
        self.mach_speed = float(data.get("mach_speed", self.mach_speed))
        self._restart_detail = "unit restarted"
        gap = now - float(data.get("saved_at", now))
        self.alarms.log_event(f"unit restarted (last saved {gap:.1f} s before)", now, source="unit")

    def close(self) -> None:
        """Save a last time and close the store."""
        self._save()
        if self.store is not None:
            self.store.close()


def request_to_dict(r: Request) -> dict[str, Any]:
    if isinstance(r, CommandRequest):
        return {"kind": "command", "cmd": r.cmd, "source": r.source}
    if isinstance(r, ModeRequest):
        return {"kind": "mode", "mode": r.mode, "source": r.source}
    return {"kind": "complete", "em": r.em, "state": r.state, "sequence": r.sequence}


def request_from_dict(d: dict[str, Any]) -> Request:
    kind = d["kind"]
    if kind == "command":
        return CommandRequest(int(d["cmd"]), d["source"])
    if kind == "mode":
        return ModeRequest(d["mode"], d["source"])
    return CompleteReport(d["em"], int(d["state"]), int(d["sequence"]))


#: Every input method of Unit (what ``on_input`` reports and ``apply_input`` accepts).
INPUTS = frozenset({
    "command", "set_mode", "step", "em_complete", "em_seen", "em_lost", "em_interlock", "em_count",
    "set_em_active", "set_alarm", "ack_alarms", "reset_alarms", "reset_times", "reset_counters",
    "set_mach_speed", "set_parameters", "set_product", "set_remote_enabled", "set_interlock", "advance",
    "shutdown",
})  # fmt: skip


def product_from_dict(d: dict[str, Any]) -> Product:
    return Product(
        d["product_id"],
        tuple(Descriptor(**v) for v in d.get("process_variables", [])),
        tuple(
            Ingredient(i["ingredient_id"], tuple(Descriptor(**v) for v in i.get("parameter", [])))
            for i in d.get("ingredients", [])
        ),
    )


def product_to_dict(p: Product) -> dict[str, Any]:
    return {
        "product_id": p.product_id,
        "process_variables": [d.__dict__ for d in p.process_variables],
        "ingredients": [
            {"ingredient_id": i.ingredient_id, "parameter": [d.__dict__ for d in i.parameter]}
            for i in p.ingredients
        ],
    }


__all__ = [
    "CommandRequest",
    "CompleteReport",
    "ModeRequest",
    "Stats",
    "StatusMark",
    "Transition",
    "Trigger",
    "Unit",
    "request_from_dict",
    "request_to_dict",
]
