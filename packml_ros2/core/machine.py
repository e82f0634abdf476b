"""The PackML unit's state machine (:class:`UnitMachine`): it drives the state machine the rule
book (:mod:`.rules`) declares, from commands, mode requests and State Complete, and owns the
evaluation (deadlines, settling, publication, persistence) every input goes through. The other
inputs are concerns of their own, composed into :class:`~.unit.Unit`: the EMs' (:mod:`.em_inputs`),
alarms (:mod:`.alarm_inputs`), the Admin and Command tags (:mod:`.tag_inputs`); so are what falls
due on its own (:mod:`.deadline_handlers`) and the views built on request (:mod:`.unit_views`).
A mode change, once accepted, is :mod:`.mode_change`'s (a base of the machine: it owns the mode's
fields, which the fast path reads); the transition record and the output queue are
:mod:`.outputs`'.

A unit is pure Python: it takes its clock as a parameter and never looks at wall time itself.
Every input (a command, a mode request, an EM report, an alarm...) first advances the engine to the
clock's time, firing due deadlines (timeouts, dwell, periodic admin and saves) *at their own
times*; the results depend only on the inputs and their times, so replaying recorded inputs on the
recorded clock reproduces the outputs exactly.

What a unit is made of (each part owns its state; together they are the engine's state):

- the machine: ``state``, ``sequence`` (this module), ``mode`` and the mode change in process
  (:class:`~.mode_change.ModeChanges`);
- :class:`~.equipment.Equipment` (EMs, State Complete aggregation), :class:`~.alarms.AlarmManager`,
  :class:`~.times.ModeStateTimes`, :class:`~.counters.Counters`,
  :class:`~.interlocks.Interlocks`, :class:`~.stopreason.StopReasons`;
- :class:`~.deadlines.Deadlines` (what is due when) and :class:`~.publication.Publication` (the
  output queue and its coalescing); the :class:`~.rules.Alert` the parts keep their bits in.

Outputs are queued and taken with :meth:`Unit.drain`: transitions, status and alarm-list changes,
admin snapshots due, and log lines. The ROS node (``packml_ros2.unit_node``) publishes them.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from types import MethodType
from typing import Any, ClassVar, NamedTuple

from . import inputlog
from .alarms import AlarmDef, AlarmEvent, AlarmManager
from .config import Descriptor, Product, UnitConfig
from .counters import Counters
from .deadlines import Deadlines, Due
from .durable import Durable, document
from .equipment import Equipment
from .fastpath import attach as attach_fast_paths
from .interlocks import (
    EXTERNAL_KEY,
    LEGACY_SOURCE,
    STOP_ID_BLOCKED,
    STOP_ID_STARVED,
    Interlocks,
    interlock_refusal,
    interlock_source,
)
from .mode_change import ModeChanges
from .numbers import Cmd, State, command_name, state_name
from .outputs import Outputs, Transition
from .packtags import build_admin
from .persistence import Store
from .publication import Publication as _Publication
from .publication import StatusMark
from .reasons import Answer, Reason
from .recipes import Recipes
from .requests import CommandRequest, CompleteReport, ModeRequest, Request, priority
from .rules import (
    AT_ONCE_WITHOUT_EMS,
    ENTRY,
    MODE_CHANGE_NOT_ALLOWED_SECONDS,
    OPERATOR,
    SETTLE,
    SUPERSEDED_SENTENCE,
    Alert,
    Entry,
    Trigger,
    Verdict,
    Watch,
    command_priority,
    is_remote,
    locked_refusal,
    mode_change_refusal,
    rules_of,
)
from .stopreason import StopReasons
from .times import ModeStateTimes

S, C = State, Cmd
Clock = Callable[[], float]


class _Frame:
    """What closes every input's frame (:meth:`UnitMachine._input`): settle, publish, journal."""

    __slots__ = ("_leave",)

    def __init__(self, leave: Callable[[], None]) -> None:
        self._leave = leave

    def __enter__(self) -> None:
        return None

    def __exit__(self, kind: type[BaseException] | None, value: object, tb: object) -> None:
        if kind is None:
            self._leave()


class _Cmd(NamedTuple):
    """A command inside the engine (alarm reaction, EM loss, interlock), with what caused it."""

    cmd: int
    source: str
    trigger: Trigger = Trigger.COMMAND
    detail: str = ""
    alarm: AlarmEvent | None = None
    stop_id: int = 0


@dataclass(slots=True)
class Stats:
    """Counts for diagnostics."""

    commands_rejected: int = 0
    stale_reports: int = 0
    sc_ignored: int = 0
    bad_reports: int = 0


# Enum members as module globals for the hot paths below: attribute access on an Enum class costs
# about 100 ns, a global about 20 ns, and these run on every transition.
_ACCEPTED, _NOT_ALLOWED = Reason.ACCEPTED, Reason.COMMAND_NOT_ALLOWED
_T_COMMAND, _T_INTERLOCK = Trigger.COMMAND, Trigger.INTERLOCK
_REMOTE = int(Watch.REMOTE)
_RESET_ALARMS, _CLEAR_FIRST_OUT = int(Entry.RESET_ALARMS), int(Entry.CLEAR_FIRST_OUT)
_REARM, _STOP = int(Entry.REARM), int(Entry.STOP)
#: Entry actions that are all a re-arm when no alarm is listed and no first-out is kept.
_NOT_QUIET = ~(_REARM | _RESET_ALARMS | _CLEAR_FIRST_OUT)

_REPORT_OK = Answer(True, Reason.ACCEPTED, "State Complete accepted")
#: At most this many rounds of _settle (each applies a queued command or a State Complete).
_SETTLE_BOUND = range(1000)


class UnitMachine(ModeChanges):
    """The state machine of one PackML unit and the evaluation of its inputs (the base of
    :class:`~.unit.Unit`: build that). ``Unit(config, clock)``; optionally a
    :class:`~.persistence.Store`.

    Inputs are methods (:meth:`command`, :meth:`set_mode`, :meth:`em_complete`, ...) answering
    with an :class:`~.reasons.Answer`; outputs are taken with :meth:`drain`; :meth:`advance` fires
    due deadlines (:meth:`next_deadline` says when the next one is due).
    """

    # Past 30 attributes CPython gives up the compact per-instance dict and every attribute access
    # on the hot paths gets slower; slots keep them fast (bench/engine.py).
    __slots__ = (  # noqa: RUF023 (grouped by concern, not sorted)
        # the machine
        # (the mode and its change: ModeChanges)
        "state", "sequence", "entered_at", "_sc_refused",
        # Command and Status tags
        "remote_enabled", "cntrl_cmd", "mach_speed", "parameters", "products",
        "remote_commands",
        # parts
        "config", "rules", "_clock", "store", "_durable", "_not_durable", "on_input", "restored",
        "alert", "stats", "times",
        "counters", "alarms", "equipment", "interlocks", "stops", "deadlines", "publication",
        "recipes",
        # the compiled rules the hot paths index, and configuration they test
        "_accepted", "_sc", "_timed",
        # evaluation
        "_t", "_advance_to", "_frame", "_internal", "_step_winner", "_restart_detail",
        "_handlers", "_out",
        # caches
        "_valid_cache", "_rev", "_strays",
        # compatibility
        "legacy_interlock_source",
    )  # fmt: skip

    #: What each kind of deadline does, a handler taking (the unit, the deadline's data): the
    #: table of :mod:`.deadline_handlers`, where the handlers are.
    DEADLINE_HANDLERS: ClassVar[Mapping[Due, Callable[[Any, Any], None]]] = {}

    def __init__(self, config: UnitConfig, clock: Clock, store: Store | None = None) -> None:
        self.config = config
        self.rules = rules = rules_of(config)
        attach_fast_paths(rules)  # (once per rules: the runs' generated code)
        self._clock = clock
        self.store = store
        #: Called with (time, input name, arguments) for every input: the replay log.
        self.on_input: Callable[[float, str, dict[str, Any]], None] | None = None
        now = float(clock())  # the clock returns seconds as a float
        self._t = self._advance_to = now
        self.state = S.STOPPED
        ModeChanges.__init__(self, config, rules.accepted)
        self.sequence = 0
        self.entered_at = now
        self._sc_refused = -1  # the sequence whose State Complete was refused
        self.remote_enabled = config.remote_commands_enabled
        self.cntrl_cmd = 0
        self.mach_speed = config.mach_speed
        self.parameters: list[Descriptor] = list(config.parameters)
        self.products: list[Product] = list(config.products)
        self.remote_commands: dict[int, tuple[int, int]] = {}  # interface number -> (cmd, value)
        self.alert = Alert()
        self.stats = Stats()
        self.times = ModeStateTimes(now, self.mode, self.state)
        self.counters = Counters(config.sizes.counters, dict(config.counters))
        self.alarms = AlarmManager(
            {(a.id, a.value): a for a in config.alarms},
            dict(config.reactions),
            config.sizes.alarms,
            config.sizes.warnings,
            config.sizes.history,
            self.alert,
        )
        self.equipment = Equipment(self.alert)
        for em_cfg in config.equipment_modules:
            ignore = not self._lost_reaction(em_cfg.lost_reaction)
            self.equipment.add(em_cfg.name, True, em_cfg.active, em_cfg.lost_reaction, ignore)
        self.interlocks = Interlocks(self.alert)
        self.recipes = Recipes(config.recipes)
        self.stops = StopReasons(config.planned_stop_ids)
        self.deadlines = Deadlines()
        self._out = Outputs()  # the output queue (drain)
        self.publication = _Publication(
            self._queue, self.deadlines, self._status_key, self._admin_key, self.alarms
        )
        self._accepted = rules.accepted
        self._sc = rules.sc
        self._timed = frozenset(config.timeouts) | frozenset(config.min_dwell)
        self._internal: list[_Cmd] = []
        self._valid_cache: dict[tuple[Any, ...], tuple[Cmd, ...]] = {}
        self._strays: set[str] = set()  # unknown EMs refused registration (logged once)
        self._rev = 0  # +1 on status-relevant changes not covered by other version counters
        self._step_winner: tuple[int, str] | None = None
        self._restart_detail = "unit started"
        #: interlock transitions name their source "interlock", as input logs of schema 1 and
        #: before recorded it (replay sets it for those; core/interlocks.py)
        self.legacy_interlock_source = False
        self._frame = _Frame(self._leave)
        self._handlers: Mapping[Due, Callable[[Any], None]] = {
            kind: MethodType(handler, self) for kind, handler in self.DEADLINE_HANDLERS.items()
        }
        self._durable = (
            None
            if store is None
            else Durable(
                store,
                self.times,
                self.counters,
                self.alarms,
                self.stops,
                self._producing,
                lambda: self.recipes.current.id,
            )
        )
        self._not_durable = ""  # why the admin data is not on the disk, as the alarm says
        self._restore(now)
        self._transition(S.STOPPED, Trigger.RESTART, source="unit", detail=self._restart_detail)
        self._journal()
        self.publication.baseline()  # the start-up status is the baseline for later changes
        if store is not None:
            self._every(Due.SAVE, config.persistence_period)
        self._every(Due.ADMIN, config.admin_period)

    @property
    def stop_reason(self) -> AlarmEvent | None:
        """``Admin.StopReason``: the first event of the last stop."""
        return self.stops.reason

    # ==============================================================================================
    # Inputs. Each advances to the clock first; ``on_input`` sees (time, name, arguments) for replay.
    # ==============================================================================================
    def _enter(self) -> None:
        pub = self.publication
        if pub.status_key[0] != self.sequence:  # a transition was published since the last key
            pub.baseline()
        now = self._clock()
        if now >= self.deadlines.next_due:
            self._advance(now)
        elif now > self._t:
            self._t = now

    def _record(self, d: inputlog.InputDef, *values: Any) -> None:
        """Log an input (its values in the order of the schema's fields): the replay log."""
        if self.on_input is not None:
            self.on_input(self._t, d.name, inputlog.fields_of(d, values))

    def _leave(self) -> None:
        self._settle()
        self.publication.flush(self._t, self.sequence)
        self._journal()

    def _input(self, d: inputlog.InputDef | None, *values: Any) -> _Frame:
        """The frame of one input, ``with self._input(inputlog.X, *values): ...``: on entry the
        engine is brought to the clock's time (what falls due fires at its own time) and the
        input is recorded (``values`` in the order of ``d``'s fields, encoded as ``d`` says; no
        ``d``: not recorded); on leaving, however the body returns, what follows is settled,
        published and journalled. (An exception leaves it unsettled, as it found it.)
        :meth:`command` and :meth:`em_complete`, the inputs that run most, frame themselves
        with the same steps, taking only those their case needs."""
        self._enter()
        if d is not None and self.on_input is not None:
            self.on_input(self._t, d.name, inputlog.fields_of(d, values))
        return self._frame

    def command(self, cmd: int, source: str = OPERATOR) -> Answer:
        """A state command (``Command.CntrlCmd`` + ``CmdChangeRequest``)."""
        now = self._clock()
        if now >= self.deadlines.next_due:
            if self.publication.status_key[0] != self.sequence:
                self.publication.baseline()
            self._advance(now)
        elif now > self._t:
            self._t = now
        bits = self.alert.bits
        remote = False
        if source is not OPERATOR:  # (the default: nothing to look at)
            if not source:
                source = OPERATOR
            elif is_remote(source):
                remote = True
                if not self.remote_enabled:
                    bits |= _REMOTE
        if self.on_input is not None:
            self._record(inputlog.COMMAND, cmd, source)
        entry = self._accepted_mode[self.state].get(cmd)
        if entry is not None and not entry.watch & bits:
            # The fast path: the table accepts and no guard of this command watches anything set.
            if self.mode_change_in_process:  # (only Stop and Abort watch no mode change)
                self._abandon_mode_change(f"{command_name(cmd)} from {source}")
            if remote:
                self._note_remote(entry.cmd, source)
            # A unit without EMs follows the State Completes that come at once as compiled: the
            # run's code generated from the rules (core/fastpath.py), which answers None when
            # the unit is not quiet enough for it (then the general loop decides).
            go = entry.go
            if go is not None and (answer := go(self, source)) is not None:
                more = self.interlocks.busy
            else:
                answer = entry.answer
                self.cntrl_cmd = entry.cmd
                more = self._transition(
                    entry.final,
                    entry.trigger,
                    entry.cmd,
                    source,
                    entry.skipped,
                    "",
                    None,
                    True,
                    entry.entry,
                )
            if not more:
                # Nothing for _settle and nothing changed after the last transition, whose
                # status is published with it: that is the baseline, and stays so until the
                # next input begins (which takes the key then, see Publication.status_key).
                if self._durable is not None:
                    self._journal()
                return answer
        else:
            if self.publication.status_key[0] != self.sequence:
                self.publication.baseline()
            self._step_winner = None  # (only a refusal reads it: not on the fast path)
            answer = self._apply_command(cmd, source, self.state, None, True)
        eq, interlocks, pub = self.equipment, self.interlocks, self.publication
        if (  # anything left for _settle? (the command followed immediate State Complete itself)
            self._internal
            or self.mode_change_in_process
            or (eq.aggregating and not eq.pending)
            or interlocks.busy
        ):
            self._settle()
        if pub.status_key[0] == self.sequence or self.alarms.version != pub.alarms_seen:
            pub.flush(self._t, self.sequence)
        if self._durable is not None:
            self._journal()
        return answer

    def set_mode(self, mode: int | str, source: str = OPERATOR) -> Answer:
        """A mode change (``Command.UnitMode`` + ``UnitModeChangeRequest``), by number or name."""
        source = source or OPERATOR
        with self._input(inputlog.MODE, mode, source):
            return self._apply_mode(mode, source)

    def step(self, requests: Sequence[Request]) -> list[Answer]:
        """Several requests in one evaluation step, applied by priority: Abort > Stop > Hold >
        Suspend > other commands > mode changes > State Complete (docs/packml.md §2)."""
        with self._input(inputlog.STEP, requests):
            start_state = self.state
            self._step_winner = None
            answers: list[Answer] = [Answer.ok("")] * len(requests)
            for i in sorted(range(len(requests)), key=lambda i: priority(requests[i])):
                r = requests[i]
                if isinstance(r, CommandRequest):
                    answers[i] = self._apply_command(int(r.cmd), r.source or OPERATOR, start_state)
                elif isinstance(r, ModeRequest):
                    answers[i] = self._apply_mode(r.mode, r.source)
                else:
                    answers[i] = self._apply_report(r.em, r.state, r.sequence)
            return answers

    # -- equipment modules -------------------------------------------------------------------------
    def em_complete(self, name: str, state: int, sequence: int) -> Answer:
        """State Complete from EM ``name`` for (``state``, ``sequence``)."""
        # (_enter, inline: every EM reports every acting state, so this runs most of all)
        pub = self.publication
        if pub.status_key[0] != self.sequence:
            pub.baseline()
        now = self._clock()
        if now >= self.deadlines.next_due:
            self._advance(now)
        elif now > self._t:
            self._t = now
        if self.on_input is not None:
            self._record(inputlog.EM_STATE_COMPLETE, name, state, sequence)
        eq = self.equipment
        if eq.report(name, state, sequence):
            if eq.pending:
                # Progress only: a status shows it (coalesced, and one is due already after the
                # first report); nothing an admin or the alarm list shows changed.
                if not pub.status_due:
                    pub.flush(self._t, self.sequence)
                return _REPORT_OK
            self._settle()  # the last report: State Complete (or the mode change) follows
            pub.flush(self._t, self.sequence)
            if self._durable is not None:
                self._journal()
            return _REPORT_OK
        answer = self._refused_report(name, state, sequence)
        pub.flush(self._t, self.sequence)
        return answer

    def _locked(self, what: str, source: str) -> Answer | None:
        """The remote lock's refusal of an input that changes the unit (rules, section 4)."""
        if self.remote_enabled:
            return None
        return locked_refusal(what, source, False, self.config.name)

    def set_remote_enabled(self, enabled: bool) -> None:
        """Whether commands with a remote source are accepted (the remote lock, rules section 4)."""
        with self._input(inputlog.REMOTE, enabled):
            self.remote_enabled = bool(enabled)
            self._rev += 1

    def shutdown(self, detail: str = "") -> Answer:
        """The unit's own process is shutting down (Ctrl-C, SIGTERM): recorded as what it is, an
        event in the alarm history and, when the unit was producing (Execute or on its way
        there), its StopReason, so the restarted unit tells why it stopped. The state is not
        changed; status, alarms and admin go out at once (the process ends after this)."""
        with self._input(inputlog.SHUTDOWN, detail):
            message = (
                f"unit shut down{f' ({detail})' if detail else ''} in {state_name(self.state)}"
            )
            self.alarms.log_event(message, self._t, source="unit")
            stops = self.stops
            if stops.armed and SETTLE.get(self.state) is S.EXECUTE:
                stops.record(stops.of_shutdown(message, self._t))
                self._rev += 1
            self._status_now()
            self.publication.admin(build_admin(self, self._t), coalesced=False)
            return Answer.ok(message)

    def set_interlock(self, active: bool, reason: str = "", source: str = OPERATOR) -> Answer:
        """A line interlock from outside (the coordinator): suspend while set, unsuspend when
        cleared (``interlock_reaction: suspend``). Each source holds its own interlock, and clears
        only its own."""
        source = source or OPERATOR
        with self._input(inputlog.INTERLOCK, active, reason, source):
            return self._set_interlock(bool(active), reason, source)

    def _set_interlock(self, active: bool, reason: str, source: str) -> Answer:
        key = f"{EXTERNAL_KEY}{source}"
        name = self.config.name
        held = [
            k[len(EXTERNAL_KEY) :] for k in self.interlocks.active if k.startswith(EXTERNAL_KEY)
        ]
        refused = interlock_refusal(held, active, source, self.remote_enabled, name)
        if refused is not None:
            return refused
        if active:
            stop_id = STOP_ID_STARVED if "starv" in reason.lower() else STOP_ID_BLOCKED
            self.interlocks.set(key, reason or f"interlock from {source}", stop_id)
        else:
            self.interlocks.clear(key)
        self._rev += 1
        return Answer.ok(f"interlock from {source} {'set' if active else 'cleared'} on {name}")

    def advance(self) -> None:
        """Fire every deadline due by the clock's time (call periodically, or at
        :meth:`next_deadline`)."""
        with self._input(None):
            pass  # (the frame alone: what falls due fires as it opens, then settles)

    def clock_step(self, offset: float) -> Answer:
        """The wall clock stepped by ``offset`` seconds (NTP, an operator): the engine's timeline
        moves with it. Its deadlines (timeouts, dwell, the mode change's, the changeover's, the
        periodic admin and saves) and the starts of its running times move by ``offset`` too, so
        each keeps the seconds it had left or had run: a step forward fires no timeout, a step
        back silences nothing, and no time counts the step. Timestamps from here on are the new
        clock's. What was due by the step's instant on the old timeline (``now - offset``) fires
        first (a driver fires it one deadline at a time before, as
        :meth:`packml_ros2.driver.UnitDriver.clock_step` does); this input is taken at the
        clock's time, on the new timeline, and recorded there (the one record whose stamp may go
        back)."""
        now = float(self._clock())
        if not (math.isfinite(offset) and math.isfinite(now)):
            return Answer.no(Reason.INVALID_ARGUMENT, f"clock step {offset!r} is not a number")
        self._advance(now - offset)  # (what was due by the step, on the old timeline)
        self.deadlines.shift(offset)
        self.times.shift(offset)
        self.recipes.shift(offset)
        if self._durable is not None:
            self._durable.shift(offset)
        self.entered_at += offset
        self.mode_change_not_allowed_until += offset  # (-inf stays -inf)
        self._t += offset
        self._advance_to = now
        with self._input(inputlog.CLOCK_STEP, offset):  # (nothing is due: all moved past now)
            text = f"the wall clock stepped {offset:+.3f} s: timeouts and times go on as they were"
            self.alarms.log_event(text, self._t, source="unit")
            self._log("warn", text)
            return Answer.ok(text)

    def next_deadline(self) -> float | None:
        """When the engine has something to do next on its own (a timeout, a periodic admin...)."""
        due = self.deadlines.next_due
        return None if due == math.inf else due

    def fire_next(self, until: float) -> bool:
        """Fire the earliest deadline if it is due by ``until``; False when none is. Driving the
        engine one deadline at a time (and publishing after each) is what makes a live node and a
        replay produce the same messages (see packml_ros2.driver)."""
        if until < self.deadlines.next_due:
            return False
        if self.publication.status_key[0] != self.sequence:
            self.publication.baseline()
        self._advance_to = until
        self._fire()
        return True

    # ==============================================================================================
    # Outputs and views
    # ==============================================================================================
    def drain(self) -> Outputs:
        """Outputs since the last call, in order: ("transition", Transition), ("status",
        StatusMark), ("alarms", version), ("admin", AdminView), ("log", (level, text)).

        A status is due after every transition (publish :meth:`status_at` of the transition
        record) and at every ("status", mark) — changes that were not transitions. Marks and
        records are cheap; building the StatusView is left to the publisher."""
        out, self._out = self._out, Outputs()
        return out

    @property
    def now(self) -> float:
        return self._t

    def valid_commands(self, state: State | None = None) -> tuple[Cmd, ...]:
        """Commands an operator could issue now (cached per state, mode and situation)."""
        state = self.state if state is None else state
        key = (
            state,
            self.mode,
            self.alarms.blocking_version,
            self.equipment.roster_version,
            bool(self.interlocks.active),
            self.mode_change_in_process,
        )
        cached = self._valid_cache.get(key)
        if cached is None:
            bits = self.alert.bits
            rules = self.rules
            cached = tuple(
                Cmd(c)
                for c, entry in sorted(self._accepted[self.mode][state].items())
                if not entry.watch & bits
                or rules.check(self, state, self.mode, c, OPERATOR).reason is _ACCEPTED
            )
            if len(self._valid_cache) > 4096:
                self._valid_cache.clear()
            self._valid_cache[key] = cached
        return cached

    def state_requested(self, state: State | None = None) -> State:
        state = self.state if state is None else state
        return self.rules.settles_in(state)

    # -- what the guards read (rules.Situation) ----------------------------------------------------
    def missing_names(self) -> list[str]:
        return [em.name for em in self.equipment.missing()]

    def blocking_alarm(self, blocked: Mapping[int, frozenset[Cmd]], cmd: int) -> str | None:
        blocker = self.alarms.blocking(blocked, cmd)
        if blocker is None:
            return None
        return f"alarm {blocker.label()} with reaction {command_name(blocker.reaction)}"

    def _em_gone_from_changeover(self, name: str, reason: str) -> None:
        """EM ``name`` is lost while a changeover runs: if the changeover waits for its answer,
        that counts as its refusal now, not at the changeover's timeout
        (:class:`~.recipe_inputs.RecipeInputs` decides; a unit without it has no changeover)."""

    def recipe_change_text(self) -> str:
        c = self.recipes.changeover
        return "" if c is None else f"the changeover to recipe {c.requested.label} is in process"

    def interlock_reasons(self) -> list[str]:
        return self.interlocks.reasons()

    # ==============================================================================================
    # The state machine
    # ==============================================================================================
    def _check(self, cmd: int, source: str) -> Verdict:
        """Whether ``cmd`` from ``source`` is valid now (the checked path of the rule book)."""
        return self.rules.check(self, self.state, self.mode, cmd, source)

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
        verdict = self._check(cmd, source)
        if verdict.reason is not _ACCEPTED or verdict.final is None:
            return self._reject(cmd, source, start_state, cause, verdict)
        entry = self._accepted[self.mode][self.state][cmd]
        if self.mode_change_in_process:  # only Abort and Stop pass the guards then
            self._abandon_mode_change(f"{command_name(cmd)} from {source}")
        self.cntrl_cmd = entry.cmd
        if is_remote(source):
            self._note_remote(entry.cmd, source)
        trigger, detail = entry.trigger, ""
        if cause is not None:
            if cause.trigger is not _T_COMMAND:
                trigger = cause.trigger
            detail = cause.detail
        self._step_winner = (entry.cmd, source)
        self._transition(
            entry.final,
            trigger,
            entry.cmd,
            source,
            entry.skipped,
            detail,
            cause,
            follow,
            entry.entry,
        )
        return entry.answer

    def _reject(
        self, cmd: int, source: str, start_state: State, cause: _Cmd | None, verdict: Verdict
    ) -> Answer:
        self.stats.commands_rejected += 1
        reason = verdict.reason
        winner = self._step_winner
        if (
            winner is not None
            and reason is _NOT_ALLOWED
            and self.rules.table_verdict(start_state, self.mode, cmd).reason is _ACCEPTED
        ):
            return Answer.no(
                Reason.SUPERSEDED,
                SUPERSEDED_SENTENCE.format(
                    command=command_name(cmd),
                    winner=command_name(winner[0]),
                    source=winner[1],
                    state=state_name(self.state),
                ),
            )
        where = f"{state_name(self.state)} in {self.mode_def.name} mode"
        msg = self.rules.refusal_text(
            verdict, cmd, source, where, self.config.name, self.mode_def.name, self.valid_commands()
        )
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
        if self.equipment.report(name, state, sequence):
            return _REPORT_OK
        return self._refused_report(name, state, sequence)

    def _refused_report(self, name: str, state: int, sequence: int) -> Answer:
        """A report :meth:`Equipment.report` did not take: unknown EM, or stale (counted)."""
        if name not in self.equipment.modules:
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
        entry: int = -1,
    ) -> bool:
        """Enter ``to`` (``entry``: its :class:`~.rules.Entry` actions as compiled, -1 to look them
        up). With ``follow``, then take State Complete as long as it is immediate (nothing to
        wait for: no EM owes it, no dwell, nothing queued, no mode change): exactly what
        :meth:`_settle` would do next, in one loop (:meth:`command` follows a compiled
        :class:`~.rules.Run` itself where it can). Only for a request alone in its step: in a
        :meth:`step`, the other requests are judged in the state the first one reached.

        Returns, with ``follow``, whether :meth:`_settle` may have something left (a queued
        command, a mode change, a State Complete it must refuse, an interlock); False when the
        unit stopped in a state that waits."""
        t = self._t
        mode = self.mode
        out = self._out.append
        eq = self.equipment
        stops = self.stops
        interlocks = self.interlocks
        alarms = self.alarms
        timed = self._timed
        # Equipment.begin decides who owes State Complete. Without an EM nobody does
        # (AT_ONCE_WITHOUT_EMS); it only needs to know whether the state the unit stops in
        # aggregates (the first EM to register brings it up to date: see em_seen).
        with_ems = eq.modules
        first = to  # the states entered (first, between, to), for the times
        between: tuple[State, ...] = ()
        if entry < 0:
            entry = 0
            for s in (*skipped, to):
                entry |= int(ENTRY.get(s, 0))
        # The interlock's claim on the suspension is judged at every entry while it holds one.
        special = trigger is _T_INTERLOCK or interlocks.suspended
        # Only entry actions change the alarm list: it is judged once, and after entry actions.
        alarms_changed = alarms.version != self.publication.alarms_seen
        # The machine's fields are written when the loop is done (nothing in it reads them).
        frm, seq = self.state, self.sequence
        while True:
            seq += 1
            if special or entry:
                if (
                    not special
                    and entry & _REARM
                    and not entry & _NOT_QUIET
                    and not alarms.current
                    and not alarms.first_out_by_category
                ):
                    stops.armed = True  # all _entry_actions would do: nothing to reset
                else:
                    self._entry_actions(to, skipped, trigger, cmd, source, cause)
                    special = interlocks.suspended
                    alarms_changed = alarms.version != self.publication.alarms_seen
            out(
                (
                    "transition",
                    (t, seq, (frm, to, mode, mode, trigger, cmd, source, skipped, detail)),
                )
            )
            if alarms_changed:  # the alarm list goes with the transition
                self.publication.alarms_changed()
                alarms_changed = False
            due = eq.begin(to, seq) if with_ems else to in AT_ONCE_WITHOUT_EMS
            if timed and to in timed:  # (an empty set is cheaper to test than to search)
                config = self.config
                if to in config.timeouts:
                    self.deadlines.at(t + config.timeouts[to], Due.TIMEOUT, (to, seq))
                if to in config.min_dwell:
                    self.deadlines.at(t + config.min_dwell[to], Due.DWELL, (to, seq))
                    due = False  # State Complete waits for the dwell (_settle)
            # State Complete, at once? (the order of _settle: queued commands, mode change, SC)
            if not (follow and due):
                more = False
                break
            if self._internal or self.mode_change_in_process:  # (nothing in this loop sets them)
                more = True
                break
            final, skipped, trigger, enabled, entry = self._sc[mode][to]  # type: ignore[misc]
            if not enabled:
                more = True  # _settle refuses it (and says so)
                break
            if to is not first:
                between += (to,)  # (a third state in one step: rare)
            frm = to
            to = final
            cmd = 0
            source = "unit"
            detail = ""
            cause = None
        self.sequence = seq
        self.state = to
        self.entered_at = t
        self.times.enter_states(
            t, first, to, between, stops.planned_reason and stops.planned(mode, to)
        )
        if not with_ems and eq.aggregating is not (to in AT_ONCE_WITHOUT_EMS):
            eq.begin(to, seq)  # (without EMs only whether the state aggregates matters)
        return more or interlocks.busy

    def _entry_actions(
        self,
        to: State,
        skipped: tuple[State, ...],
        trigger: Trigger,
        cmd: int,
        source: str,
        cause: _Cmd | None,
    ) -> None:
        """The :data:`~.rules.ENTRY` actions of the skipped states and ``to``, in order, and the
        interlock's claim on the suspension."""
        for s in (*skipped, to) if skipped else (to,):
            flags = ENTRY.get(s, 0)
            if not flags:
                continue
            alarms = self.alarms
            if flags & _RESET_ALARMS and alarms.current:
                alarms.reset()
            if flags & _CLEAR_FIRST_OUT and alarms.first_out_by_category:
                alarms.clear_first_out()
            if flags & _REARM:
                self.stops.armed = True
            elif flags & _STOP and self.stops.armed:
                self.stops.record(self._stop_reason_of(cause or _Cmd(cmd, source, trigger)))
        interlocks = self.interlocks
        if interlocks.suspended or trigger is _T_INTERLOCK:
            interlocks.entered(to, skipped, trigger is _T_INTERLOCK)

    def _stop_reason_of(self, cause: _Cmd) -> AlarmEvent:
        if cause.alarm is not None:
            return cause.alarm
        if cause.trigger is Trigger.INTERLOCK:
            return self.stops.of_interlock(
                cause.cmd, cause.source, cause.detail, cause.stop_id or STOP_ID_BLOCKED, self._t
            )
        return self.stops.of_command(cause.cmd, cause.source, self._t)

    def _planned(self) -> bool:
        """Whether the unit is in a planned stop now (OEE)."""
        return self.stops.planned(self.mode, self.state)

    def _sc_ready(self) -> bool:
        """Every EM that must report has (the caller checked); dwell and refusal remain."""
        if self._sc_refused == self.sequence:
            return False
        min_dwell = self.config.min_dwell
        if min_dwell and self.state in min_dwell:
            return self._t >= self.entered_at + min_dwell[self.state]
        return True

    def _refuse_state_complete(self, final: State) -> None:
        """State Complete would lead into a state disabled in this mode: ignore it (counted)."""
        self.stats.sc_ignored += 1
        self._sc_refused = self.sequence
        self._log(
            "info",
            f"State Complete of {state_name(self.state)} ignored: {state_name(final)} is disabled "
            f"in {self.mode_def.name}",
        )

    def _settle(self) -> None:
        """Apply what follows from the current situation until nothing more does: queued internal
        commands (alarm reactions, EM loss, interlocks) by priority, then State Complete."""
        eq = self.equipment
        interlocks = self.interlocks
        for _ in _SETTLE_BOUND:
            if self._internal:
                queue = sorted(self._internal, key=lambda r: command_priority(r.cmd))
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
                and (  # (_sc_ready without the call in the common case: no dwell configured)
                    (not self.config.min_dwell and self._sc_refused != self.sequence)
                    or self._sc_ready()
                )
            ):
                final, skipped, trigger, enabled, entry = self._sc[self.mode][self.state]  # type: ignore[misc]  # aggregating: an acting state
                if enabled:
                    self._transition(final, trigger, 0, "unit", skipped, "", None, True, entry)
                    continue
                self._refuse_state_complete(final)
            if interlocks.busy and self._interlock_action():
                continue
            return

    def _interlock_action(self) -> bool:
        if not self.config.interlock_reaction:
            return False
        action = self.interlocks.action(self.state, self.sequence)
        if action is None:
            return False
        cmd, detail, stop_id, key = action
        source = LEGACY_SOURCE if self.legacy_interlock_source else interlock_source(key)
        self._internal.append(_Cmd(cmd, source, Trigger.INTERLOCK, detail, stop_id=stop_id))
        return True

    # -- modes (the rest of a mode change: core/mode_change.py) ---------------------------------
    def _apply_mode(self, mode: int | str, source: str) -> Answer:
        """A mode change request (by number or name) from ``source``: judged, then begun."""
        target = self._find_mode(mode)
        if target is None:
            configured = ", ".join(f"{n} {m.name}" for n, m in sorted(self.config.modes.items()))
            return Answer.no(
                Reason.MODE_UNKNOWN,
                f"mode {mode!r} is not configured on {self.config.name} (now {state_name(self.state)} "
                f"in {self.mode_def.name} mode; configured: {configured})",
            )
        refused = self._locked(f"mode change to {target.name}", source)
        if refused is not None:
            return refused
        if self.mode_change_in_process:
            return Answer.no(
                Reason.MODE_CHANGE_IN_PROCESS,
                f"mode change to {target.name} refused: change to "
                f"{self._mode_name(self.mode_requested)} still in process",
            )
        if target.number == self.mode:
            return Answer.ok(f"already in {target.name}")
        changeover = self.recipes.changeover
        if changeover is not None:
            return Answer.no(
                Reason.RECIPE_CHANGE_IN_PROCESS,
                f"mode change to {target.name} refused: the changeover to recipe "
                f"{changeover.requested.label} is in process",
            )
        why = mode_change_refusal(self.mode_def, target, self.state)
        if why is not None:
            self.mode_change_not_allowed_until = self._t + MODE_CHANGE_NOT_ALLOWED_SECONDS
            self.deadlines.at(self.mode_change_not_allowed_until, Due.LAMP_OFF)
            self._rev += 1
            self._status_now()
            return Answer.no(
                Reason.MODE_CHANGE_NOT_ALLOWED,
                f"mode change {self.mode_def.name} -> {target.name} not allowed in "
                f"{state_name(self.state)}: {why}",
            )
        self.command_unit_mode = target.number
        self.mode_requested = target.number
        self._mode_changing(True)
        self._mode_source = source
        self.sequence += 1
        self.equipment.begin_mode_change(self.sequence)
        self.deadlines.at(
            self._t + self.config.mode_change_timeout, Due.MODE_TIMEOUT, self.sequence
        )
        self._status_now()
        return Answer.ok(f"mode change {self.mode_def.name} -> {target.name} accepted")

    # -- alarms inside -----------------------------------------------------------------------------
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

    def _lost_reaction(self, configured: int | None) -> int:
        return self.config.em_lost_reaction if configured is None else configured

    # -- deadlines ---------------------------------------------------------------------------------
    def _every(self, kind: Due, period: float) -> None:
        self.deadlines.every(self._t, self._advance_to, kind, period)

    def _fire(self) -> None:
        """Fire the earliest deadline at its own time, then settle and publish."""
        when, kind, data = self.deadlines.pop()
        self._t = max(self._t, when)
        self._handlers[kind](data)
        self._leave()

    def _advance(self, now: float) -> None:
        self._advance_to = now
        deadlines = self.deadlines
        while now >= deadlines.next_due:
            self._fire()
        self._t = max(self._t, now)

    # -- publication -------------------------------------------------------------------------------
    def _status_key(self) -> tuple[int, ...]:
        """What a status shows changed when this changed."""
        return (self.sequence, self._rev, self.equipment.version, self.alarms.version)

    def _admin_key(self) -> tuple[int, ...]:
        """What an admin shows changed (discretely: times change all the time) when this did."""
        return (self.sequence, self.counters.version, self.alarms.version, self._rev)

    def _queue(self, item: tuple[str, Any]) -> None:
        """An output of the publication (the unit's queue is swapped at every drain)."""
        self._out.append(item)

    def _status_now(self) -> None:
        self.publication.status_now(self._t, self.state, self.sequence)

    def _log(self, level: str, text: str) -> None:
        self.publication.log(level, text)

    def _changed(self) -> None:
        """Something a status shows changed that no part's version counts."""
        self._rev += 1

    # -- persistence (core/durable.py) ------------------------------------------------------------
    def document(self) -> dict[str, Any]:
        """What persistence stores: everything of the admin data, never the state."""
        return document(
            self.times,
            self.counters,
            self.alarms,
            self.stops,
            self.sequence,
            self.mach_speed,
            self._t,
            self._producing(),
            self.recipes.current.id,
        )

    def _producing(self) -> bool:
        """In Execute or on its way there, with the StopReason armed: a crash now is a stop
        (core/durable.py). A shutdown records its StopReason, which disarms it."""
        return self.stops.armed and SETTLE.get(self.state) is S.EXECUTE

    def checkpoint(self, now: float) -> None:
        """Journal the times as of ``now`` (the node calls this every
        :data:`~.durable.TIME_CHECKPOINT` seconds): a process killed between inputs loses at most
        that much time. Not an input: nothing changes, nothing is published or recorded."""
        if self._durable is not None:
            self._durable.checkpoint(max(now, self._t))

    def _journal(self) -> None:
        """Write-ahead: the input's durable changes reach the store before it is answered."""
        durable = self._durable
        if durable is not None:
            durable.journal(self.sequence, self.mode, self.mach_speed, self._t)
            if durable.failing != self._not_durable:
                self._persistence_changed(durable.failing)

    def _snapshot(self, closing: bool = False) -> None:
        durable = self._durable
        if durable is not None:
            durable.snapshot(self.sequence, self.mode, self.mach_speed, self._t, closing)
            if durable.failing != self._not_durable:
                self._persistence_changed(durable.failing)

    @property
    def not_durable(self) -> str:
        """Why what the unit answers now is not on the disk ('' = it is): a store that cannot
        be written (a full disk); the node says so in every answer."""
        return self._not_durable

    def _persistence_changed(self, why: str) -> None:
        """The store started or stopped failing: the ``persistence_failing`` alarm follows."""
        sa = self.config.system_alarms
        was, self._not_durable = self._not_durable, why
        if why and not was:
            self._log(
                "warn",
                f"persistence failing: {why}; retrying (the admin data since is not durable)",
            )
            message = f"persistence failing: {why}"[:240]
            self._raise(
                AlarmDef(sa.persistence_failing, 1, message, sa.persistence_failing_category),
                source="unit",
            )
        elif not why:
            self._log("info", "persistence recovered: the admin data is on the disk again")
            self.alarms.clear(sa.persistence_failing, 1, self._t)
        else:
            return
        self._settle()
        self.publication.flush(self._t, self.sequence)
        if self._durable is not None:  # (the alarm's events, once the store takes them)
            self._durable.journal(self.sequence, self.mode, self.mach_speed, self._t)

    def _restore(self, now: float) -> None:
        self.restored: dict[str, Any] | None = None
        if self._durable is None:
            return
        restored = self._durable.restore(now)
        data = self.restored = restored.document
        if data is not None:
            self.sequence = restored.sequence
            if restored.mach_speed is not None:
                self.mach_speed = restored.mach_speed
            self._restart_detail = "unit restarted"
            if restored.recipe is not None:
                problem = self.recipes.restore_current(restored.recipe)
                if problem:
                    self._log("warn", problem)
            gap = now - float(data.get("saved_at", now))
            self.alarms.log_event(
                f"unit restarted (last saved {gap:.1f} s before)", now, source="unit"
            )
            if restored.producing:  # it crashed: why it stopped is that, not the last stop
                self.stops.set(
                    self.stops.of_crash(
                        f"unit process ended without shutting down (crash or kill) while producing; "
                        f"restarted {gap:.1f} s after its last save",
                        now,
                    )
                )
                self.stops.armed = False
        sa = self.config.system_alarms
        for n, problem in enumerate(restored.problems, 1):
            self._log("warn", f"persistence: {problem}")
            d = AlarmDef(
                sa.store_unreadable,
                n,
                f"persistence: {problem}"[:240],
                sa.store_unreadable_category,
            )
            self._raise(d, source="unit")
            self.alarms.clear(d.id, d.value, now)

    def close(self) -> None:
        """Save a last snapshot and close the store (an orderly end: not a crash)."""
        self._snapshot(closing=True)
        if self.store is not None:
            self.store.close()


__all__ = [
    "CommandRequest",
    "CompleteReport",
    "ModeRequest",
    "Request",
    "Stats",
    "StatusMark",
    "Transition",
    "Trigger",
    "UnitMachine",
]
