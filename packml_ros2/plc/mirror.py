"""What a PLC's PackML object says, as a unit of this package would say it (pure: no OPC UA
session, no rclpy; the clock is passed in).

The bridge (:mod:`.node`) hands :class:`Mirror` the values of the PLC's OPC 30050 object as plain
Python (:mod:`.link` converts them), keyed by their browse path below the object, e.g.
``Status/UnitModeCurrent`` or ``BaseStateMachine/MachineState/CurrentState/Id``. The mirror:

- reads the PackML state from the three nested state machines (BaseStateMachine > MachineState >
  ExecuteState): the ``CurrentState/Id`` of each (the state objects of the official NodeSet,
  :mod:`packml_ros2.opcua.nodeset`), else its ``Number`` or its name. The walk goes inwards only
  through the composite states (Cleared, Running), so a stale value of an inactive sub machine is
  never read. A batch that moved an outer machine into its composite state without a value for the
  inner machine is held back until the inner value arrives or :data:`HOLD` seconds passed;
- turns every state or mode change into a transition with a sequence number and the trigger a
  unit would give it: the command the bridge sent (with its source), State Complete (an acting
  state ending where the model says), an alarm (the PLC's fresh StopReason or a new active alarm,
  as ``alarm:<id>``), or a command given at the PLC itself (source ``plc``);
- answers what a unit's status carries: valid commands, StateRequested, disabled states (from the
  unit's configuration: its modes and model describe the PLC's), alarms as
  :class:`~packml_ros2.core.alarms.AlarmEvent`, the stop reason;
- judges a request as a unit does, by the unit's rule book (:func:`packml_ros2.core.rules.rules_of`:
  valid commands, targets, the guards (the remote lock, a mode change in process, an interlock)
  and the refusal's sentence): nothing of the rules is written here again. A mode the
  configuration does not know is judged by the rules of the unit's initial mode.
"""

from __future__ import annotations

import datetime as _dt
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from ..core.alarms import AlarmEvent, Kind
from ..core.config import UnitConfig
from ..core.numbers import ACTING, WAIT, Cmd, State, command_name, state_name
from ..core.reasons import Reason
from ..core.rules import COMMANDS, SETTLE, Rules, Trigger, command_priority, rules_of
from ..core.rules import REACTIONS as RULE_REACTIONS
from ..core.unit import Transition
from ..opcua.mapping import COMMAND_METHODS
from ..opcua.nodeset import MachineDef, PackMLModel

S = State
#: Seconds a state change waits for the inner machine's value or for its cause.
HOLD = 0.3
#: Seconds a command the bridge sent stays expected when the PLC does not react.
EXPECT_FOR = 10.0
#: The command a PLC-made transition is taken for when several lead there: the engine's priority
#: (the rule book's, ties in command order).
PRIORITY = tuple(sorted(COMMANDS, key=command_priority))
#: The commands an alarm's reaction gives: a PLC-made transition of theirs waits for its cause.
REACTIONS = frozenset(Cmd(c) for c in RULE_REACTIONS.values() if c)

#: The variables the bridge follows, relative to the unit object (those a PLC does not have are
#: left out). The three ``CurrentState`` (and their ``Id``) are mandatory in OPC 30050, as are
#: UnitModeCurrent, MachSpeed, CurMachSpeed, EquipmentBlocked and EquipmentStarved.
MACHINES = (
    "BaseStateMachine",
    "BaseStateMachine/MachineState",
    "BaseStateMachine/MachineState/ExecuteState",
)
STATUS = (
    "UnitModeCurrent",
    "UnitModeChangeInProcess",
    "StateRequested",
    "StateChangeInProcess",
    "MachSpeed",
    "CurMachSpeed",
    "EquipmentBlocked",
    "EquipmentStarved",
    "MaterialInterlocked",
    "Parameter",
    "Product",
    "RemoteParameter",
)
ADMIN = (
    "Alarm",
    "AlarmExtent",
    "AlarmHistory",
    "AlarmHistoryExtent",
    "Warning",
    "WarningExtent",
    "StopReason",
    "StopReasonExtent",
    "ModeCurrentTime",
    "ModeCumulativeTime",
    "StateCurrentTime",
    "StateCumulativeTime",
    "ProdConsumedCount",
    "ProdProcessedCount",
    "ProdDefectiveCount",
    "AccTimeSinceReset",
    "MachDesignSpeed",
    "Parameter",
)
PATHS: tuple[str, ...] = (
    *(f"{m}/CurrentState{leaf}" for m in MACHINES for leaf in ("", "/Id", "/Number")),
    *(f"Status/{name}" for name in STATUS),
    *(f"Admin/{name}" for name in ADMIN),
)
REQUIRED = (f"{MACHINES[0]}/CurrentState", "Status/UnitModeCurrent")


@dataclass
class Expected:
    """A command the bridge sent, until the PLC's transition for it shows."""

    cmd: Cmd
    source: str
    from_state: State
    reach: tuple[State, ...]  # where it leads: its first state, then by State Complete
    at: float
    trigger: Trigger = Trigger.COMMAND
    detail: str = ""


@dataclass
class PlcSituation:
    """What the rule book's guards read (:class:`packml_ros2.core.rules.Situation`) of a PLC unit:
    the bridge's remote lock and interlocks, the PLC's mode change; no EMs and no alarm of the
    bridge's (the PLC judges its own)."""

    remote_enabled: bool
    mode_change_in_process: bool = False
    interlocks: tuple[str, ...] = ()

    def missing_names(self) -> list[str]:
        return []

    def blocking_alarm(self, blocked: Mapping[int, frozenset[Cmd]], cmd: int) -> str | None:
        return None

    def interlock_reasons(self) -> list[str]:
        return list(self.interlocks)

    def mode_change_text(self) -> str:
        return "a mode change is in process at the PLC"

    def recipe_change_text(self) -> str:
        return ""  # (OPC 30050 v1.01 has no recipes: the PLC guards its own changeover)


@dataclass
class Mirror:
    """The PLC unit ``config`` as the bridge sees it; ``model``: the OPC 30050 NodeSet."""

    config: UnitConfig
    model: PackMLModel
    values: dict[str, Any] = field(default_factory=dict)
    state: State = S.UNDEFINED
    mode: int = 0
    sequence: int = 0
    expected: list[Expected] = field(default_factory=list)
    mode_request: tuple[int, str, float] | None = None  # (mode, source, at)
    cntrl_cmd: int = 0
    command_mach_speed: float = 0.0
    #: StopReason and the active alarms as they were when the current state was entered
    _baseline: tuple[Any, frozenset[tuple[int, int, float]]] = (None, frozenset())
    _unsettled_since: float | None = None
    #: a change held back (:data:`HOLD`): the states the PLC showed since, oldest first; each
    #: becomes a transition of its own (Stopping and Stopped of one publish response)
    _held: list[State] = field(default_factory=list)
    _held_settled: bool = False

    # -- the state -------------------------------------------------------------------------------
    def _place(self, machine: MachineDef, path: str) -> str | None:
        """The name of ``machine``'s current state (None: unknown)."""
        ident = self.values.get(f"{path}/CurrentState/Id")
        if isinstance(ident, int):
            found = next((s.name for s in machine.states if s.id == ident), None)
            if found is not None:
                return found
        number = self.values.get(f"{path}/CurrentState/Number")
        if isinstance(number, int) and not isinstance(number, bool):
            found = next((s.name for s in machine.states if s.number == number), None)
            if found is not None:
                return found
        name = self.values.get(f"{path}/CurrentState")
        if isinstance(name, str) and name:
            key = name.replace(" ", "").lower()
            return next((s.name for s in machine.states if s.name.lower() == key), None)
        return None

    def read_state(self, changed: Iterable[str] = ()) -> tuple[State | None, bool]:
        """The PackML state the three machines show, and whether it is settled (False: the walk
        entered a composite state whose inner machine sent nothing in this batch)."""
        changed = set(changed)
        settled = True
        entered = False
        for machine, path in zip(self.model.machines, MACHINES, strict=True):
            name = self._place(machine, path)
            if name is None:
                return None, True
            inner = f"{path}/CurrentState"
            if entered and not any(p.startswith(inner) for p in changed):
                settled = False
            if name != machine.sub_state:
                try:
                    return State[name.upper()], settled
                except KeyError:
                    return None, True
            entered = any(p.startswith(inner) for p in changed)
        return None, True

    # -- rules of the unit (its configuration describes the PLC's) -------------------------------
    @property
    def rules(self) -> Rules:
        return rules_of(self.config)

    def rules_mode(self) -> int:
        """The mode the rules judge in: the PLC's, or the initial one for a mode not configured."""
        return self.mode if self.mode in self.config.modes else self.config.initial_mode

    def valid_commands(self, state: State | None = None) -> tuple[Cmd, ...]:
        state = self.state if state is None else state
        return self.rules.valid_commands(state, self.rules_mode())

    def reach(self, state: State, cmd: Cmd) -> tuple[State, ...]:
        """Where ``cmd`` leads from ``state``: its first state, then on by State Complete up to the
        wait state (or Execute); () when it is not valid there."""
        return self.rules.reach(state, cmd)

    def _chain(self, first: State) -> tuple[State, ...]:
        return self.rules.chain(first)

    def target(self, cmd: Cmd) -> State:
        """The state ``cmd`` settles in from the current state (the current one if invalid)."""
        chain = self.reach(self.state, cmd)
        return chain[-1] if chain else self.state

    def state_requested(self) -> State:
        requested = self.values.get("Status/StateRequested")
        if isinstance(requested, int) and 0 < requested <= max(State):
            return State(requested)
        return SETTLE.get(self.state, self.state)

    def mode_change_in_process(self) -> bool:
        return self.values.get("Status/UnitModeChangeInProcess") is True

    def judge(self, cmd: int, source: str, situation: PlcSituation) -> tuple[Reason, str] | None:
        """Why ``cmd`` from ``source`` is refused now by the unit's rules, as a unit says it
        (None: valid): the rule book's guards and table, and its sentence."""
        rules, mode = self.rules, self.rules_mode()
        verdict = rules.check(situation, self.state, mode, cmd, source)
        if verdict.reason is Reason.ACCEPTED:
            return None
        text = rules.refusal_text(
            verdict,
            cmd,
            source,
            self.where(),
            self.config.name,
            self.mode_name(mode),
            self.valid_commands(),
        )
        return verdict.reason, text

    def refusal(self, cmd: int) -> str | None:
        """Why ``cmd`` is not valid now by the unit's table (no guard), as a unit says it."""
        found = self.judge(cmd, "operator", PlcSituation(remote_enabled=True))
        return None if found is None else found[1]

    def where(self) -> str:
        return f"{state_name(self.state)} in {self.mode_name(self.mode)} mode"

    def mode_name(self, mode: int) -> str:
        mode_def = self.config.modes.get(mode)
        return mode_def.name if mode_def is not None else f"MODE_{mode}"

    def states_disabled(self) -> int:
        mode_def = self.config.modes.get(self.mode)
        return sum(1 << int(s) for s in mode_def.disabled) if mode_def is not None else 0

    def method_for(self, cmd: Cmd) -> str:
        """The OPC 30050 method of ``cmd`` in the current state: the innermost active machine
        that has it (Reset in Complete is ExecuteState's, in Stopped MachineState's)."""
        name = COMMAND_METHODS[cmd]
        places = self.model.places(self.state)
        having = [
            i for i, m in enumerate(self.model.machines) if any(x.name == name for x in m.methods)
        ]
        active = [i for i in having if places[i] is not None]
        machine = self.model.machines[(active or having)[-1]]
        return f"{machine.path}/{name}"

    # -- commands the bridge sends ---------------------------------------------------------------
    def expect(
        self,
        cmd: Cmd,
        source: str,
        now: float,
        trigger: Trigger = Trigger.COMMAND,
        detail: str = "",
    ) -> Expected:
        """Register ``cmd`` before it is sent (the PLC's change may arrive before its answer)."""
        entry = Expected(cmd, source, self.state, self.reach(self.state, cmd), now, trigger, detail)
        self.expected.append(entry)
        return entry

    def forget(self, entry: Expected) -> None:
        """The PLC refused ``entry`` (or never answered)."""
        if entry in self.expected:
            self.expected.remove(entry)

    # -- values arrive ---------------------------------------------------------------------------
    def connected(self, values: Mapping[str, Any], now: float, detail: str) -> list[Transition]:
        """A (new) session: every value at once. The first transition is RESTART (from the state
        last known, UNDEFINED at the start)."""
        self.values = dict(values)
        self.expected.clear()
        self.mode_request = None
        self._unsettled_since = None
        self._held.clear()
        state, _ = self.read_state()
        mode = self._mode()
        before, self.state = self.state, state if state is not None else S.UNDEFINED
        from_mode, self.mode = self.mode, mode
        self._rebaseline()
        return [
            self._record(
                now, before, self.state, from_mode, Trigger.RESTART, source="plc", detail=detail
            )
        ]

    def update(self, values: Mapping[str, Any], now: float) -> list[Transition]:
        """A batch of changed values (one publish response): the transitions it shows."""
        self.values.update(values)
        out: list[Transition] = []
        state, settled = self.read_state(values)
        if state is None or state == self.state:
            self._unsettled_since = None
            self._held.clear()
        else:
            if self._held and self._held[-1] != state and not self._held_settled:
                self._held.pop()  # a composite state read without its inner value: not a state
            if not self._held or self._held[-1] != state:
                self._held.append(state)
            self._held_settled = settled
            waited = self._unsettled_since is not None and now - self._unsettled_since >= HOLD
            if settled or waited or len(self._held) > 1:
                while self._held:
                    change = self._state_change(self._held[0], now, may_wait=not waited)
                    if change is None:
                        break
                    out.append(change)
                    del self._held[0]
            if not self._held:
                self._unsettled_since = None
            elif self._unsettled_since is None:
                self._unsettled_since = now
        mode = self._mode()
        if mode != self.mode:
            source = "plc"
            if self.mode_request is not None and self.mode_request[0] == mode:
                source = self.mode_request[1]
            self.mode_request = None
            from_mode, self.mode = self.mode, mode
            out.append(
                self._record(
                    now,
                    self.state,
                    self.state,
                    from_mode,
                    Trigger.MODE,
                    source=source,
                    detail=f"{self.mode_name(from_mode)} -> {self.mode_name(mode)}",
                )
            )
        self.expected = [e for e in self.expected if now - e.at < EXPECT_FOR]
        return out

    def tick(self, now: float) -> list[Transition]:
        """A held-back state change whose inner value did not come within :data:`HOLD`."""
        if self._unsettled_since is not None and now - self._unsettled_since >= HOLD:
            return self.update({}, now)
        return []

    def _mode(self) -> int:
        value = self.values.get("Status/UnitModeCurrent")
        return int(value) if isinstance(value, int) and not isinstance(value, bool) else 0

    def _state_change(self, to: State, now: float, may_wait: bool = False) -> Transition | None:
        """The transition to ``to``; None when it may wait (``may_wait``) for its cause: a PLC
        that stops by itself writes its StopReason and alarm with the state, but they may come
        in the next publish."""
        frm = self.state
        for i, entry in enumerate(self.expected):
            if entry.from_state == frm and to in entry.reach:
                del self.expected[: i + 1]
                skipped = entry.reach[: entry.reach.index(to)]
                self.cntrl_cmd = int(entry.cmd)
                return self._enter(
                    now, frm, to, entry.trigger, int(entry.cmd), entry.source, skipped, entry.detail
                )
        if frm in ACTING:
            chain = self._chain(self.config.table.state_complete[frm])
            if to in chain:
                return self._enter(
                    now, frm, to, Trigger.STATE_COMPLETE, 0, "plc", chain[: chain.index(to)]
                )
        for cmd in PRIORITY:
            chain = self.reach(frm, cmd)
            if to in chain:
                skipped = chain[: chain.index(to)]
                cause = self._fault()
                if cause is not None:
                    return self._enter(
                        now,
                        frm,
                        to,
                        Trigger.ALARM,
                        int(cmd),
                        f"alarm:{cause.id}",
                        skipped,
                        cause.message,  # like a unit: the alarm's message (its ID is in the source)
                    )
                if may_wait and cmd in REACTIONS:
                    return None
                return self._enter(
                    now,
                    frm,
                    to,
                    Trigger.COMMAND,
                    int(cmd),
                    "plc",
                    skipped,
                    f"{command_name(cmd)} given at the PLC",
                )
        return self._enter(
            now,
            frm,
            to,
            Trigger.COMMAND,
            0,
            "plc",
            (),
            f"the PLC went from {state_name(frm)} to {state_name(to)}, "
            "which the unit's model has no transition for",
        )

    def _fault(self) -> AlarmEvent | None:
        """What took the PLC out of its state by itself: a StopReason set since it entered the
        state, else an alarm that became active since then."""
        reason = self.values.get("Admin/StopReason")
        if reason != self._baseline[0]:
            event = alarm_event(reason, Kind.ALARM)
            if event is not None:
                return event
        for ev in self.alarms():
            if ev.trigger and _alarm_key(ev) not in self._baseline[1]:
                return ev
        return None

    def _enter(
        self,
        now: float,
        frm: State,
        to: State,
        trigger: Trigger,
        command: int,
        source: str,
        skipped: Iterable[State] = (),
        detail: str = "",
    ) -> Transition:
        self.state = to
        if to in WAIT or to is S.EXECUTE:
            self._rebaseline()
        return self._record(
            now, frm, to, self.mode, trigger, command, source, tuple(skipped), detail
        )

    def _rebaseline(self) -> None:
        self._baseline = (
            self.values.get("Admin/StopReason"),
            frozenset(_alarm_key(ev) for ev in self.alarms() if ev.trigger),
        )

    def _record(
        self,
        now: float,
        frm: State,
        to: State,
        from_mode: int,
        trigger: Trigger,
        command: int = 0,
        source: str = "",
        skipped: tuple[State, ...] = (),
        detail: str = "",
    ) -> Transition:
        self.sequence += 1
        return Transition(
            now,
            self.sequence,
            frm,
            to,
            from_mode,
            self.mode,
            trigger,
            command,
            source,
            skipped,
            detail,
        )

    # -- alarms ------------------------------------------------------------------------------------
    def alarms(self) -> list[AlarmEvent]:
        return _events(self.values.get("Admin/Alarm"), Kind.ALARM)

    def warnings(self) -> list[AlarmEvent]:
        return _events(self.values.get("Admin/Warning"), Kind.WARNING)

    def history(self) -> list[AlarmEvent]:
        return _events(self.values.get("Admin/AlarmHistory"), Kind.ALARM)

    def stop_reason(self) -> AlarmEvent | None:
        return alarm_event(self.values.get("Admin/StopReason"), Kind.ALARM)

    def banner(self) -> str:
        first = next((ev for ev in self.alarms() if ev.trigger), None)
        return f"{first.id}/{first.value} {first.message}" if first is not None else ""


def _alarm_key(ev: AlarmEvent) -> tuple[int, int, float]:
    return (ev.id, ev.value, ev.time)


def epoch(value: Any) -> float | None:
    """An OPC UA DateTime (datetime) as seconds since 1970; None for the null DateTime."""
    if isinstance(value, _dt.datetime):
        if value.year < 1971:
            return None
        if value.tzinfo is None:
            value = value.replace(tzinfo=_dt.UTC)
        return float(value.timestamp())
    if isinstance(value, int | float) and not isinstance(value, bool) and value > 0:
        return float(value)
    return None


def alarm_event(value: Any, kind: Kind) -> AlarmEvent | None:
    """A PackMLAlarmDataType (plain: a mapping of its fields) as an alarm event (None: empty)."""
    if not isinstance(value, Mapping):
        return None
    ident = value.get("ID")
    if not isinstance(ident, int) or ident == 0:
        return None
    time = epoch(value.get("DateTime")) or 0.0
    trigger = bool(value.get("Trigger"))
    return AlarmEvent(
        id=ident,
        value=int(value.get("Value") or 0),
        message=str(value.get("Message") or ""),
        category=int(value.get("Category") or 0),
        kind=kind,
        time=time,
        source="plc",
        trigger=trigger,
        latched=True,
        ack_time=epoch(value.get("AckDateTime")),
    )


def _events(values: Any, kind: Kind) -> list[AlarmEvent]:
    if not isinstance(values, list):
        return []
    return [ev for v in values if (ev := alarm_event(v, kind)) is not None]


# -- refusals of the PLC ---------------------------------------------------------------------------
#: An OPC UA status code of a refused method call -> the reason code a unit gives (Result).
REFUSALS: Mapping[str, Reason] = {
    "BadInvalidState": Reason.COMMAND_NOT_ALLOWED,
    "BadNotExecutable": Reason.COMMAND_NOT_ALLOWED,
    "BadUserAccessDenied": Reason.UNAUTHORIZED,
    "BadNotWritable": Reason.UNAUTHORIZED,
    "BadOutOfRange": Reason.INVALID_ARGUMENT,
    "BadInvalidArgument": Reason.INVALID_ARGUMENT,
    "BadTypeMismatch": Reason.INVALID_ARGUMENT,
    "BadArgumentsMissing": Reason.INVALID_ARGUMENT,
    "BadTooManyArguments": Reason.INVALID_ARGUMENT,
    "BadNothingToDo": Reason.NOTHING_TO_DO,
    "BadNotImplemented": Reason.NOT_SUPPORTED,
    "BadNotSupported": Reason.NOT_SUPPORTED,
    "BadMethodInvalid": Reason.NOT_SUPPORTED,
    "BadNodeIdUnknown": Reason.NOT_SUPPORTED,
    "BadNoCommunication": Reason.UNIT_UNAVAILABLE,
    "BadCommunicationError": Reason.UNIT_UNAVAILABLE,
    "BadTimeout": Reason.UNIT_UNAVAILABLE,
    "BadServerNotConnected": Reason.UNIT_UNAVAILABLE,
    "BadSessionClosed": Reason.UNIT_UNAVAILABLE,
    "BadSessionIdInvalid": Reason.UNIT_UNAVAILABLE,
    "BadConnectionClosed": Reason.UNIT_UNAVAILABLE,
    "BadShutdown": Reason.UNIT_UNAVAILABLE,
}
#: ... where a mode request reads them otherwise.
MODE_REFUSALS: Mapping[str, Reason] = {
    **REFUSALS,
    "BadInvalidState": Reason.MODE_CHANGE_NOT_ALLOWED,
    "BadOutOfRange": Reason.MODE_UNKNOWN,
}


def plc_refusal(
    what: str, where: str, status: str, text: str, mode: bool = False
) -> tuple[Reason, str]:
    """The reason code and sentence of a request the PLC refused with ``status`` (its name) and,
    if it gave one, its diagnostic ``text``."""
    table = MODE_REFUSALS if mode else REFUSALS
    reason = table.get(status, Reason.COMMAND_NOT_ALLOWED)
    because = f": {text}" if text else ""
    return reason, f"{what} refused by the PLC in {where} ({status}{because})"
