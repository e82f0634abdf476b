"""The rule book: everything that decides a PackML transition, declared once, as data.

Where is a transition decided? Here. The engine (:mod:`.unit`) and the faces (HMI diagram, OPC UA
AvailableStates/AvailableTransitions, the coordinator's targets) read these declarations through a
:class:`Rules` compiled once per unit configuration; nothing else restates them.

1. **Transition table** (docs/packml.md §2): TR88-2022 and the 2015 model, the Stop and Abort sets,
   the Hold/Complete per-state masks.
2. **Modes** (docs/packml.md §3): disabled-state implications, skipping disabled acting states,
   the mode-change matrix.
3. **Priority** of requests in one evaluation step.
4. **Sources**: the kinds of source a request names, which are remote, and the remote lock
   over every input that changes the unit (and who may change the lock).
5. **Guards**: situations that refuse a command the table allows (mode change in process,
   remote commands disabled, a missing EM, a reacting alarm, an interlock), each with its reason
   code and the sentence an operator reads.
6. **Entry actions**: what entering a state does besides the transition (alarm reset, first-out
   clear, stop reason).
7. **Equipment modules** (docs/packml.md §4): who owes State Complete, who is excused, when one may
   register at run time, when an EM switched active joins.
8. **Compiled** (:class:`Rules`): the per-unit lookups the engine's fast path indexes, and the
   questions faces ask (:meth:`Rules.edges`, :meth:`Rules.available_states`,
   :meth:`Rules.available_transitions`, :meth:`Rules.valid_commands`, :meth:`Rules.target`,
   :meth:`Rules.settles_in`, :meth:`Rules.mode_change_refusal`).

How the engine uses the guards: every guard *watches* one part of the unit's situation (a
:class:`Watch` bit). The unit keeps an :class:`Alert` with a bit set for every watched part that is
not empty now (an EM is missing, a reacting alarm is active, ...). A compiled table entry carries
the bits of the guards that apply to its command, so the fast path accepts a command when its entry
exists and ``entry.watch & alert.bits == 0``: no guard can refuse. Otherwise the checked path
evaluates the guards in :data:`GUARDS` order, around the table's own verdict.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from enum import IntEnum, IntFlag
from typing import Any, NamedTuple, Protocol

from .numbers import ACTING, NUM_STATES, Cmd, Mode, State, command_name, names_of
from .reasons import Answer, Reason

S, C = State, Cmd

# ==================================================================================================
# 1. The transition table (docs/packml.md §2)
# ==================================================================================================
#: (from, command) -> to, TR88-2022, without the Stop and Abort sets; Hold and Complete are
#: masked per model (``HOLD_FROM``, ``COMPLETE_FROM``) or per configuration.
COMMANDS_2022: Mapping[tuple[State, Cmd], State] = {
    (S.STOPPED, C.RESET): S.RESETTING,
    (S.IDLE, C.START): S.STARTING,
    (S.EXECUTE, C.HOLD): S.HOLDING,
    (S.EXECUTE, C.SUSPEND): S.SUSPENDING,
    (S.EXECUTE, C.COMPLETE): S.COMPLETING,
    (S.COMPLETE, C.RESET): S.RESETTING,
    (S.HELD, C.UNHOLD): S.UNHOLDING,
    (S.HELD, C.COMPLETE): S.COMPLETING,
    (S.SUSPENDED, C.UNSUSPEND): S.UNSUSPENDING,
    (S.SUSPENDED, C.HOLD): S.HOLDING,
    (S.SUSPENDED, C.COMPLETE): S.COMPLETING,
    (S.ABORTED, C.CLEAR): S.CLEARING,
}
#: from -> to on State Complete (acting states only). Execute's SC ends the production run.
STATE_COMPLETE: Mapping[State, State] = {
    S.RESETTING: S.IDLE,
    S.STARTING: S.EXECUTE,
    S.EXECUTE: S.COMPLETING,
    S.COMPLETING: S.COMPLETE,
    S.HOLDING: S.HELD,
    S.UNHOLDING: S.EXECUTE,
    S.SUSPENDING: S.SUSPENDED,
    S.UNSUSPENDING: S.EXECUTE,
    S.STOPPING: S.STOPPED,
    S.ABORTING: S.ABORTED,
    S.CLEARING: S.STOPPED,
}
ALL_STATES: frozenset[State] = frozenset(s for s in State if s is not S.UNDEFINED)
COMMANDS: tuple[Cmd, ...] = tuple(c for c in Cmd if c)
#: Stop -> Stopping from every state except these.
STOP_EXCEPT: frozenset[State] = frozenset(
    {S.STOPPING, S.STOPPED, S.ABORTING, S.ABORTED, S.CLEARING}
)
#: Abort -> Aborting from every state except these.
ABORT_EXCEPT: frozenset[State] = frozenset({S.ABORTING, S.ABORTED})
#: The states Hold and Complete are accepted in, per model (Siemens holdCmdCfg/completeCmdCfg);
#: a configuration may set them explicitly (``hold_from``, ``complete_from``).
HOLD_FROM = {"2022": frozenset({S.EXECUTE, S.SUSPENDED}), "2015": frozenset({S.EXECUTE})}
COMPLETE_FROM = {
    "2022": frozenset({S.EXECUTE, S.HELD, S.SUSPENDED}),
    "2015": frozenset({S.EXECUTE}),
}
#: The states a configuration's ``hold_from`` may name (not a Hold state itself, nor a stopping,
#: stopped or aborting one) and its ``complete_from`` (Execute, and the states around it).
HOLD_CONFIGURABLE: frozenset[State] = frozenset(State) - {
    S.UNDEFINED, S.HOLDING, S.HELD, S.STOPPING, S.STOPPED, S.ABORTING, S.ABORTED, S.CLEARING,
}  # fmt: skip
COMPLETE_CONFIGURABLE: frozenset[State] = frozenset({
    S.EXECUTE, S.HELD, S.SUSPENDED, S.HOLDING, S.SUSPENDING, S.UNHOLDING, S.UNSUSPENDING,
    S.STARTING,
})  # fmt: skip
MODELS = ("2022", "2015")


def _settle_of(state: State) -> State:
    while state in STATE_COMPLETE and state is not S.EXECUTE:
        state = STATE_COMPLETE[state]
    return state


#: The wait state each state settles in when nothing intervenes (``Status.StateRequested``):
#: State Complete followed through acting states; Execute is where production settles.
SETTLE: Mapping[State, State] = {s: _settle_of(s) for s in ALL_STATES}


@dataclass(frozen=True)
class TransitionTable:
    """Where commands and State Complete lead. Immutable; build with :func:`build_table`."""

    model: str
    commands: Mapping[tuple[State, Cmd], State]
    state_complete: Mapping[State, State]

    def target(self, state: State, cmd: Cmd) -> State | None:
        """The state command ``cmd`` leads to from ``state``, or None when it is not valid there."""
        return self.commands.get((state, cmd))

    def valid_commands(self, state: State) -> tuple[Cmd, ...]:
        return tuple(c for c in Cmd if (state, c) in self.commands)


def build_table(
    model: str = "2022",
    hold_from: Iterable[State] | None = None,
    complete_from: Iterable[State] | None = None,
) -> TransitionTable:
    """The table of ``model`` with optional explicit Hold and Complete masks."""
    if model not in MODELS:
        raise ValueError(f"model must be one of {', '.join(MODELS)}, not {model!r}")
    hold = frozenset(hold_from) if hold_from is not None else HOLD_FROM[model]
    complete = frozenset(complete_from) if complete_from is not None else COMPLETE_FROM[model]
    commands: dict[tuple[State, Cmd], State] = {
        key: to for key, to in COMMANDS_2022.items() if key[1] not in (C.HOLD, C.COMPLETE)
    }
    commands.update({(s, C.HOLD): S.HOLDING for s in hold})
    commands.update({(s, C.COMPLETE): S.COMPLETING for s in complete})
    commands.update({(s, C.STOP): S.STOPPING for s in ALL_STATES - STOP_EXCEPT})
    commands.update({(s, C.ABORT): S.ABORTING for s in ALL_STATES - ABORT_EXCEPT})
    assert set(STATE_COMPLETE) == ACTING
    return TransitionTable(model, commands, STATE_COMPLETE)


# ==================================================================================================
# 2. Modes (docs/packml.md §3)
# ==================================================================================================
#: Disabling a wait state disables the acting states that only serve it.
IMPLIED_DISABLED: Mapping[State, frozenset[State]] = {
    S.HELD: frozenset({S.HOLDING, S.UNHOLDING}),
    S.SUSPENDED: frozenset({S.SUSPENDING, S.UNSUSPENDING}),
    S.COMPLETE: frozenset({S.COMPLETING}),
}


class ModeRules(Protocol):
    """What the rules need of a mode (``modes.ModeDef``)."""

    @property
    def number(self) -> int: ...
    @property
    def name(self) -> str: ...
    @property
    def disabled(self) -> frozenset[State]: ...
    @property
    def change_allowed(self) -> frozenset[State]: ...


def corrected_disabled(states: Iterable[State]) -> frozenset[State]:
    """Apply the implication rules. Mandatory states are the caller's to refuse (config errors)."""
    out = set(states)
    for wait, implied in IMPLIED_DISABLED.items():
        if wait in out:
            out |= implied
    return frozenset(out)


def resolve(
    first: State, disabled: frozenset[State], state_complete: Mapping[State, State]
) -> tuple[State, tuple[State, ...]]:
    """Skip-through: where the unit ends up when sent to ``first`` — disabled acting states are
    passed through to their State Complete successor. Returns (final state, skipped states). The
    final state may be a disabled wait state: a command is then refused (STATE_DISABLED), State
    Complete ignored."""
    skipped: list[State] = []
    state = first
    while state in disabled and state in ACTING:
        skipped.append(state)
        state = state_complete[state]
    return state, tuple(skipped)


def mode_change_refusal(current: ModeRules, target: ModeRules, state: State) -> str | None:
    """Why a change from ``current`` to ``target`` in ``state`` is not allowed, or None: a change
    is accepted iff the state is allowed in both modes and not disabled in the target."""
    if state not in current.change_allowed:
        allowed = ", ".join(s.name for s in sorted(current.change_allowed)) or "no state"
        return f"{current.name} allows mode changes only in {allowed}"
    if state not in target.change_allowed:
        allowed = ", ".join(s.name for s in sorted(target.change_allowed)) or "no state"
        return f"{target.name} allows mode changes only in {allowed}"
    if state in target.disabled:
        return f"{state.name} is disabled in {target.name}"
    return None


#: How long ``mode_change_not_allowed`` stays up after a refused mode change (seconds).
MODE_CHANGE_NOT_ALLOWED_SECONDS = 3.0

# ==================================================================================================
# 3. Priority in one evaluation step (docs/packml.md §2)
# ==================================================================================================
#: Abort > Stop > Hold > Suspend > other commands, then mode changes, then State Complete.
PRIORITY: Mapping[int, int] = {C.ABORT: 0, C.STOP: 1, C.HOLD: 2, C.SUSPEND: 3}
OTHER_COMMANDS, MODE_REQUESTS, STATE_COMPLETE_REPORTS = 4, 5, 6


def command_priority(cmd: int) -> int:
    return PRIORITY.get(cmd, OTHER_COMMANDS)


# ==================================================================================================
# 4. Sources: who asks, and the remote lock
# ==================================================================================================
OPERATOR = "operator"  #: the source of requests that name none (an empty source)


@dataclass(frozen=True)
class SourceKind:
    """A kind of source: the part of ``kind:name`` before the colon."""

    kind: str
    remote: bool  #: subject to the remote lock (``remote_commands_enabled``)
    caller: bool  #: a service caller may name it (the others are the unit's own inputs)
    what: str


#: Every kind of source. A request's ``source`` is ``<kind>`` or ``<kind>:<name>`` (the name: 1..64
#: of ``A-Z a-z 0-9 _ . @ -``); an empty source is the local operator. Faces label themselves:
#: the HMI ``hmi:<user>``, OPC UA ``opcua:<user>``, the coordinator ``remote:coordinator`` (its
#: commands) and ``coordinator`` (its interlocks).
SOURCE_KINDS: Mapping[str, SourceKind] = {
    k.kind: k
    for k in (
        SourceKind("operator", False, True, "a person at the machine (ros2 service call, packml)"),
        SourceKind("hmi", True, True, "the browser HMI, hmi:<user>"),
        SourceKind("opcua", True, True, "the OPC UA server, opcua:<user>"),
        SourceKind("mqtt", True, True, "the MQTT Sparkplug B edge node, mqtt:<client id>"),
        SourceKind("coordinator", True, True, "the cell coordinator's interlocks"),
        SourceKind("remote", True, True, "a line controller, MES or script, remote:<who>"),
        SourceKind("em", False, False, "an EM's command request or alarm, em:<name>"),
        SourceKind("unit", False, False, "the unit itself (State Complete, timeouts)"),
        SourceKind("alarm", False, False, "an alarm's reaction, alarm:<id>"),
        SourceKind(
            "interlock",
            False,
            False,
            "a line interlock's Suspend or Unsuspend, "
            "interlock:em:<name> (the unit's own EM) or interlock:<setter>",
        ),
        SourceKind("plc", False, False, "a PLC unit's own transitions"),
    )
}
#: Kinds the remote lock lets through; "" is an empty source (the operator). Anything else is
#: remote, including what no kind names: the lock fails closed (``REMOTE:x``, `` remote``).
LOCAL_KINDS: frozenset[str] = frozenset({"", *(k for k, d in SOURCE_KINDS.items() if not d.remote)})
#: Kinds a caller may name, in the order a refusal lists them.
CALLER_KINDS: tuple[str, ...] = tuple(k for k, d in SOURCE_KINDS.items() if d.caller)
MAX_SOURCE_NAME = 64
_NAME_CHARS = frozenset("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789_.@-")


def is_remote(source: str) -> bool:
    """Whether an input from ``source`` is remote: accepted only while the unit's
    ``remote_commands_enabled`` is true (the remote lock). Fails closed: a source of no local
    kind is remote."""
    return source.partition(":")[0] not in LOCAL_KINDS


def remote_locked(source: str, remote_enabled: bool) -> bool:
    """The remote lock: an input from a remote source while remote commands are disabled (judged
    for commands by the ``remote`` guard, for every other input that changes the unit by
    :func:`locked_refusal`)."""
    return not remote_enabled and is_remote(source)


def source_refusal(source: str) -> str | None:
    """Why a caller may not send ``source`` (None: it may): the grammar above, exactly (no case,
    no spaces, no kind a caller may not name)."""
    if not source:
        return None
    kind, colon, name = source.partition(":")
    if kind not in SOURCE_KINDS or not SOURCE_KINDS[kind].caller:
        shown = source if len(source) <= 40 and source.isprintable() else f"{source[:40]!r}..."
        return (
            f"source {shown!r} is not one of {', '.join(CALLER_KINDS)} (as kind or "
            "kind:name, lower case; empty = operator)"
        )
    if colon and not is_source_name(name):
        return f"the name in source {kind}:... must be {SOURCE_NAME_GRAMMAR}"
    return None


SOURCE_NAME_GRAMMAR = f"1..{MAX_SOURCE_NAME} of A-Z a-z 0-9 _ . @ -"


def is_source_name(name: str) -> bool:
    """Whether ``name`` fits the name part of a source (a user name a face sends as it is)."""
    return 0 < len(name) <= MAX_SOURCE_NAME and _NAME_CHARS.issuperset(name)


def source_of(kind: str, name: str = "") -> str:
    """The source a face sends for ``name`` (a user): ``kind:name``, the name's characters outside
    the grammar replaced by ``_`` and cut to its length; ``kind`` alone without a name."""
    if kind not in SOURCE_KINDS:
        raise ValueError(f"no source kind {kind!r}")
    clean = "".join(c if c in _NAME_CHARS else "_" for c in name[:MAX_SOURCE_NAME])
    return f"{kind}:{clean}" if clean else kind


#: Which inputs the remote lock guards: every input that changes the unit (commands by the
#: ``remote`` guard below, the rest by :func:`locked_refusal`). Reading (query_alarms) is free;
#: so is a source clearing its own interlock (``interlock`` is setting one:
#: :func:`.interlocks.interlock_refusal`).
LOCKED_INPUTS: tuple[str, ...] = (
    "command", "mode", "alarm", "alarm.ack", "alarm.reset", "times.reset", "counters.reset",
    "speed", "parameters", "products", "em.active", "interlock",
)  # fmt: skip
#: The sentence of an input refused by the lock (``what``: the input as people say it).
LOCKED_SENTENCE = (
    "{what} from {source} refused: remote commands are disabled on {unit} (parameter "
    "remote_commands_enabled; only a local source switches it)"
)


def locked_refusal(what: str, source: str, remote_enabled: bool, unit: str) -> Answer | None:
    """The refusal of an input that changes the unit, from ``source``, while the lock holds
    (None: it passes the lock)."""
    if not remote_locked(source, remote_enabled):
        return None
    return Answer(
        False, Reason.REMOTE_DISABLED, LOCKED_SENTENCE.format(what=what, source=source, unit=unit)
    )


def lock_change_refusal(source: str, unit: str) -> Answer | None:
    """The lock itself (``remote_commands_enabled``) is changed only from a local source."""
    if not is_remote(source):
        return None
    return Answer(
        False,
        Reason.UNAUTHORIZED,
        f"remote_commands_enabled of {unit} is switched only from a local source "
        f"(the operator at the machine), not from {source}",
    )


# ==================================================================================================
# 5. Guards: situations that refuse what the table allows
# ==================================================================================================
#: Commands that start motion: refused while an active EM is missing, a reacting alarm is active
#: or (Unsuspend) a line interlock still holds the unit.
MOTION: frozenset[Cmd] = frozenset({C.RESET, C.START, C.UNHOLD, C.UNSUSPEND})
#: While an alarm with this reaction is active, these commands are refused: a fault reaction
#: never lets new motion start before its cause is gone; Abort's also refuses Clear.
BLOCKED_BY_REACTION: Mapping[int, frozenset[Cmd]] = {
    C.ABORT: MOTION | {C.CLEAR},
    C.STOP: MOTION,
    C.HOLD: MOTION,
    C.SUSPEND: MOTION,
}
#: Fault commands pass a mode change in process (which is then abandoned): docs/packml.md §2,
#: "Abort -> Aborting from every state".
FAULT_COMMANDS: frozenset[Cmd] = frozenset({C.ABORT, C.STOP})


class Watch(IntFlag):
    """A part of the unit's situation a guard reads; :class:`Alert` holds the non-empty ones."""

    REMOTE = 1  #: remote commands are disabled (and the command is remote)
    MODE_CHANGE = 2  #: a mode change is in process
    EM_MISSING = 4  #: an active EM whose loss is not ignored is offline
    ALARM = 8  #: an active alarm with a reaction
    INTERLOCK = 16  #: a line interlock holds the unit
    RECIPE = 32  #: a recipe changeover is in process


class Alert:
    """The :class:`Watch` bits of a unit that are set now. The parts keep their bit (the
    equipment, the alarms, the interlocks, the unit for mode changes); the fast path reads
    ``bits``."""

    __slots__ = ("bits",)

    def __init__(self) -> None:
        self.bits = 0

    def set(self, watch: Watch, on: bool) -> None:
        bit = int(watch)  # (a plain int: IntFlag operators run Python code)
        self.bits = (self.bits | bit) if on else (self.bits & ~bit)


class Situation(Protocol):
    """What guards read of a unit."""

    @property
    def remote_enabled(self) -> bool: ...
    @property
    def mode_change_in_process(self) -> bool: ...
    def missing_names(self) -> list[str]: ...
    def blocking_alarm(self, blocked: Mapping[int, frozenset[Cmd]], cmd: int) -> str | None: ...
    def interlock_reasons(self) -> list[str]: ...
    def mode_change_text(self) -> str: ...
    def recipe_change_text(self) -> str: ...


@dataclass(frozen=True)
class Guard:
    """A situation that refuses commands the table allows.

    ``refuses(situation, cmd, source)`` returns the detail of the refusal, or None; it is only
    called when the :class:`Watch` bit is set (or on the checked path). ``sentence`` is formatted
    with ``command``, ``source``, ``where``, ``unit``, ``detail``; " (valid now: ...)" follows."""

    name: str
    reason: Reason
    commands: frozenset[Cmd]
    watch: Watch
    before_table: bool  #: judged before the table: its reason wins over the table's
    sentence: str
    refuses: Callable[[Situation, int, str], str | None]


def _remote(s: Situation, cmd: int, source: str) -> str | None:
    return "" if remote_locked(source, s.remote_enabled) else None


def _mode_change(s: Situation, cmd: int, source: str) -> str | None:
    return s.mode_change_text() if s.mode_change_in_process else None


def _em_missing(s: Situation, cmd: int, source: str) -> str | None:
    return ", ".join(s.missing_names()) or None


def _alarm(s: Situation, cmd: int, source: str) -> str | None:
    return s.blocking_alarm(BLOCKED_BY_REACTION, cmd)


def _recipe(s: Situation, cmd: int, source: str) -> str | None:
    return s.recipe_change_text() or None


def _interlock(s: Situation, cmd: int, source: str) -> str | None:
    return "; ".join(s.interlock_reasons()) or None


#: Every guard, in the order they are judged. The table's verdict (unknown command, not allowed,
#: target state disabled) comes after the ``before_table`` ones.
GUARDS: tuple[Guard, ...] = (
    Guard(
        "remote", Reason.REMOTE_DISABLED, frozenset(COMMANDS), Watch.REMOTE, True,
        "{command} from {source} refused: remote commands are disabled on {unit} "
        "(parameter remote_commands_enabled); now {where}",
        _remote,
    ),
    Guard(
        "mode_change", Reason.MODE_CHANGE_IN_PROCESS, frozenset(COMMANDS) - FAULT_COMMANDS,
        Watch.MODE_CHANGE, True,
        "{command} refused in {where}: {detail}",
        _mode_change,
    ),
    Guard(
        "recipe", Reason.RECIPE_CHANGE_IN_PROCESS, frozenset(COMMANDS) - FAULT_COMMANDS,
        Watch.RECIPE, False,
        "{command} refused in {where}: {detail} (only Stop and Abort pass)",
        _recipe,
    ),
    Guard(
        "em_missing", Reason.EM_MISSING, MOTION, Watch.EM_MISSING, False,
        "{command} refused in {where}: active EM {detail} offline; bring it back or switch it "
        "inactive outside PRODUCTION",
        _em_missing,
    ),
    Guard(
        "alarm", Reason.ALARM_ACTIVE, frozenset().union(*BLOCKED_BY_REACTION.values()),
        Watch.ALARM, False,
        "{command} refused in {where}: {detail} is still active",
        _alarm,
    ),
    Guard(
        "interlock", Reason.INTERLOCK_ACTIVE, frozenset({C.UNSUSPEND}), Watch.INTERLOCK, False,
        "{command} refused in {where}: interlock still active ({detail})",
        _interlock,
    ),
)  # fmt: skip
#: The table's own refusals (same fields as a guard's sentence).
TABLE_SENTENCES: Mapping[Reason, str] = {
    Reason.UNKNOWN_COMMAND: "command {number} is not a PackML command (1..10: {all}); now {where}",
    Reason.COMMAND_NOT_ALLOWED: "{command} not allowed in {where}",
    Reason.STATE_DISABLED: "{command} not allowed in {where}: {detail} is disabled in {mode}",
}
#: A command valid where its step began but not after a higher-priority one moved the unit.
SUPERSEDED_SENTENCE = (
    "{command} superseded by {winner} from {source} in the same step (now {state})"
)

# ==================================================================================================
# 5b. Reactions: what raises a command inside the unit
# ==================================================================================================
NUM_CATEGORIES = 10
#: Configuration names of reactions -> the command the unit applies (0 = none).
REACTIONS: Mapping[str, int] = {
    "none": 0,
    "abort": C.ABORT,
    "stop": C.STOP,
    "hold": C.HOLD,
    "suspend": C.SUSPEND,
}
#: Alarm category -> reaction by default: 0-1 Abort, 2-4 Stop, 5-9 none (Mitsubishi); a
#: configuration may change any category and any alarm (docs/packml.md §7). Warnings never react.
DEFAULT_REACTIONS: Mapping[int, int] = {
    0: C.ABORT,
    1: C.ABORT,
    2: C.STOP,
    3: C.STOP,
    4: C.STOP,
    **dict.fromkeys(range(5, NUM_CATEGORIES), 0),
}


def _category_of_reaction() -> dict[int, int]:
    first: dict[int, int] = {}
    for category, reaction in sorted(DEFAULT_REACTIONS.items()):
        first.setdefault(reaction, category)
    quiet = first[0]  # the first category that does not react by itself
    out = {r: first.get(r, quiet) for r in REACTIONS.values() if r}
    out[0] = NUM_CATEGORIES - 1  # no reaction: the least severe category
    return out


#: The category of an alarm the unit raises for a reaction (an EM lost, reaction ``abort``): the
#: first category whose default reaction that is (Abort 0, Stop 2); Hold and Suspend, which no
#: category has by default, the first one that does not react by itself (5: the alarm carries its
#: reaction); no reaction, the last category (9).
CATEGORY_OF_REACTION: Mapping[int, int] = _category_of_reaction()


class AlarmLike(Protocol):
    """What the alarm rules read of a configured alarm (``alarms.AlarmDef``)."""

    @property
    def category(self) -> int: ...
    @property
    def message(self) -> str: ...
    @property
    def warning(self) -> bool: ...


def override_refusal(d: AlarmLike, category: int, message: str, warning: bool | None) -> str | None:
    """A configured alarm keeps its category (so its reaction), its kind and its text, whoever
    raises it: why a raise that asks for others is refused (None: it asks for none, or for the
    configured ones; -1, '' and None mean "as configured")."""
    asked = []
    if category >= 0 and category != d.category:
        asked.append(f"category {category}")
    if message and message != d.message:
        asked.append("another message")
    if warning is not None and warning != d.warning:
        asked.append("a warning" if warning else "an alarm")
    if not asked:
        return None
    kind = "warning" if d.warning else "alarm"
    return (
        f"it is a configured {kind} (category {d.category}): its category, reaction, kind and "
        f"text are the configuration's, not {' and '.join(asked)}"
    )


#: A line interlock (an EM's Blocked/Starved, or one set from outside) asks for SUSPEND while the
#: unit is in EXECUTE, and, once every interlock is cleared, for UNSUSPEND while the unit is in
#: SUSPENDED because of one (``interlock_reaction: suspend``; ``none`` switches it off).
INTERLOCK_SUSPEND: tuple[State, Cmd] = (S.EXECUTE, C.SUSPEND)
INTERLOCK_RESUME: tuple[State, Cmd] = (S.SUSPENDED, C.UNSUSPEND)
#: The states an interlock's suspension passes through: from where it suspends, on the way (the
#: acting state of that command) and where it resumes from. Outside them the unit has left it.
INTERLOCK_PATH: frozenset[State] = frozenset(
    {INTERLOCK_SUSPEND[0], COMMANDS_2022[INTERLOCK_SUSPEND], INTERLOCK_RESUME[0]}
)

# ==================================================================================================
# 6. Entry actions: what entering a state does besides the transition
# ==================================================================================================


class Entry(IntFlag):
    RESET_ALARMS = 1  #: latched alarms that are no longer active are cleared (Mitsubishi)
    CLEAR_FIRST_OUT = 2  #: the first-outs are cleared (Mitsubishi, Omron)
    REARM = 4  #: the next stop records its StopReason again
    STOP = 8  #: records the StopReason, if armed (first event only)


ENTRY: Mapping[State, Entry] = {
    S.RESETTING: Entry.RESET_ALARMS | Entry.REARM,
    S.CLEARING: Entry.RESET_ALARMS,
    S.STARTING: Entry.CLEAR_FIRST_OUT | Entry.REARM,
    S.UNHOLDING: Entry.REARM,
    S.UNSUSPENDING: Entry.REARM,
    S.STOPPING: Entry.STOP,
    S.ABORTING: Entry.STOP,
    S.HOLDING: Entry.STOP,
    S.SUSPENDING: Entry.STOP,
}
#: A stop is planned (OEE) only while the unit stands in one of these (in Production, with a stop
#: reason in the configured planned range).
PLANNED_STOP_STATES: frozenset[State] = frozenset({S.STOPPED, S.IDLE, S.STOPPING})

# ==================================================================================================
# 7. Equipment modules (docs/packml.md §4)
# ==================================================================================================
#: States in which every active EM owes State Complete for (state, sequence); those of
#: ONLY_WITH_ACTIVE_EMS only while at least one EM is active (without one, the production run ends
#: by command). A state nobody owes State Complete for completes at once.
AGGREGATING: frozenset[State] = ACTING
ONLY_WITH_ACTIVE_EMS: frozenset[State] = frozenset({S.EXECUTE})
#: Without an EM, these complete at once.
AT_ONCE_WITHOUT_EMS: frozenset[State] = AGGREGATING - ONLY_WITH_ACTIVE_EMS
#: Fault-recovery states: EMs that went offline are excused from State Complete here.
EXCUSE_OFFLINE: frozenset[State] = frozenset({S.STOPPING, S.ABORTING, S.CLEARING})
#: An EM switched active while the unit waits in an acting state owes State Complete for that
#: state (it *joins* it): the EM base class runs the state's hook when it sees itself switched
#: active, so the unit never waits for an EM that does not know it is expected.
ACTIVATED_EM_JOINS_CURRENT_STATE = True
#: An EM not in the configuration registers at run time only where the configuration allows it
#: (``allow_registration``), and, when its own report asks (a heartbeat: the EM is alive), only
#: while the unit is at rest: outside Production, or in one of these states. Mid-production a
#: stray report (a typo, another cell's EM) would make the unit wait for it, and abort when it goes
#: silent; the EM registers with its next report once the unit rests.
REGISTRATION_AT_REST: frozenset[State] = frozenset({S.STOPPED, S.IDLE, S.ABORTED, S.COMPLETE})
#: A unit takes at most this many EMs (configured and registered): a flood of made-up names
#: registers no more.
MAX_EMS = 64


def registration_refusal(
    mode: int, state: State, allow_registration: bool, by_report: bool, count: int = 0
) -> str | None:
    """Why an unknown EM cannot register now (``by_report``: its own report asks; ``count``: the
    EMs the unit has), or None."""
    if not allow_registration:
        return "does not accept registrations (allow_registration: false)"
    if count >= MAX_EMS:
        return f"has {count} EMs, as many as a unit takes ({MAX_EMS})"
    if by_report and mode == Mode.PRODUCTION and state not in REGISTRATION_AT_REST:
        rest = ", ".join(s.name for s in sorted(REGISTRATION_AT_REST))
        return f"registers EMs by their reports in PRODUCTION only at rest ({rest}), not in {state.name}"
    return None


# ==================================================================================================
# 8. Compiled per unit
# ==================================================================================================
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


class Edge(NamedTuple):
    """One edge of the state diagram: ``trigger`` is a command, or None for State Complete."""

    from_state: State
    trigger: Cmd | None
    to_state: State
    skipped: tuple[State, ...] = ()


class Accepted(NamedTuple):
    """A compiled table entry: a command the table accepts in (mode, state)."""

    final: State
    skipped: tuple[State, ...]
    answer: Answer
    cmd: int
    trigger: Trigger  #: SKIP when states were skipped, else COMMAND
    watch: int  #: Watch bits of the guards that apply to the command
    entry: int  #: Entry flags of the skipped and final states
    run: Run | None = None  #: the State Completes that follow at once without EMs
    #: ``run`` as code, generated by the engine (:func:`.fastpath.generate`): takes (unit,
    #: source), answers, or None where the unit is not quiet enough for it
    go: Callable[[Any, str], Answer | None] | None = None


#: What follows a transition record's time and sequence: the other :class:`~.outputs.Transition`
#: fields in their order (from, to, from mode, to mode, trigger, command, source, skipped, detail).
RecordTail = tuple[State, State, int, int, Trigger, int, str, tuple[State, ...], str]


class Run(NamedTuple):
    """What follows an accepted command at once in a unit without EMs: the State Completes of
    the states that complete immediately (:data:`AT_ONCE_WITHOUT_EMS`), up to the state that
    waits. Compiled from the same :class:`ScStep` entries; none (the engine's general loop
    decides) where a state on the way is timed (timeout, minimum dwell), where State Complete
    leads into a disabled state, or where an entry action records a StopReason. The engine
    generates its fast path from it (:mod:`.fastpath`: :attr:`Accepted.go`)."""

    start: State  #: the state the command is accepted in
    mode: int
    first: State  #: the command's own final state
    skipped: tuple[State, ...]  #: the states the command skipped
    answer: Answer
    cmd: int
    trigger: Trigger  #: the command's transition's
    tail: RecordTail  #: the record tail of the command's transition, from the operator
    #: the record tails of the State Completes in order (made once: only time and sequence vary)
    tails: tuple[RecordTail, ...]
    between: tuple[State, ...]  #: the states entered after ``first`` and before ``final``
    final: State  #: where the unit waits
    entry: int  #: the Entry flags of every state entered (re-arm, alarm and first-out resets)


class ScStep(NamedTuple):
    """State Complete from an acting state in a mode."""

    final: State
    skipped: tuple[State, ...]
    trigger: Trigger  #: SKIP when states were skipped, else STATE_COMPLETE
    enabled: bool  #: the final state is enabled (else SC is ignored and counted)
    entry: int


class Verdict(NamedTuple):
    reason: Reason
    final: State | None = None
    skipped: tuple[State, ...] = ()
    detail: str = ""
    guard: Guard | None = None


class ConfigLike(Protocol):
    @property
    def table(self) -> TransitionTable: ...
    @property
    def modes(self) -> Mapping[int, Any]: ...
    @property
    def interlock_reaction(self) -> int: ...
    @property
    def timeouts(self) -> Mapping[State, float]: ...
    @property
    def min_dwell(self) -> Mapping[State, float]: ...


class Rules:
    """The rule book compiled for one unit configuration (its table and modes).

    Engine lookups (indexed, not hashed: the fast path):

    - ``accepted[mode][state]``: ``{command: Accepted}`` for what the table accepts;
    - ``refused[mode][state][command]``: the table's reason for the rest (and the final state of a
      STATE_DISABLED refusal);
    - ``sc[mode][state]``: :class:`ScStep` for acting states, None for wait states.

    Questions for faces: :meth:`edges`, :meth:`available_states`, :meth:`available_transitions`,
    :meth:`valid_commands`, :meth:`target`, :meth:`settles_in`, :meth:`command_target`,
    :meth:`mode_change_refusal`, :meth:`chain`, :meth:`reach`."""

    def __init__(
        self,
        table: TransitionTable,
        modes: Mapping[int, Any],
        interlock_reaction: int = C.SUSPEND,
        timed: frozenset[State] = frozenset(),
    ) -> None:
        self.table = table
        #: States with a timeout or a minimum dwell: no :data:`Run` goes through them.
        self.timed = timed
        self.modes = dict(modes)
        #: The guards in force: the interlock guard only where interlocks act.
        self.guards: tuple[Guard, ...] = tuple(
            g for g in GUARDS if g.name != "interlock" or interlock_reaction
        )
        self.before_table = tuple(g for g in self.guards if g.before_table)
        self.after_table = tuple(g for g in self.guards if not g.before_table)
        watch: dict[int, int] = {int(c): 0 for c in COMMANDS}
        for g in self.guards:
            for c in g.commands:
                watch[c] |= int(g.watch)
        #: Watch bits per command (the guards that can refuse it).
        self.watch: Mapping[int, int] = watch
        self.accepted: dict[int, list[dict[int, Accepted]]] = {}
        self.refused: dict[int, list[list[tuple[Reason, State | None, tuple[State, ...]]]]] = {}
        self.sc: dict[int, list[ScStep | None]] = {}
        for number, mode in self.modes.items():
            self._compile_mode(number, mode.disabled)

    def _compile_mode(self, number: int, disabled: frozenset[State]) -> None:
        table = self.table
        accepted: list[dict[int, Accepted]] = [{} for _ in range(NUM_STATES)]
        not_allowed: tuple[Reason, State | None, tuple[State, ...]] = (
            Reason.COMMAND_NOT_ALLOWED,
            None,
            (),
        )
        refused = [[not_allowed] * (len(COMMANDS) + 1) for _ in range(NUM_STATES)]
        for state in State:
            for cmd in COMMANDS:
                first = table.target(state, cmd)
                if first is None:
                    continue
                final, skipped = resolve(first, disabled, table.state_complete)
                if final in disabled:
                    refused[state][cmd] = (Reason.STATE_DISABLED, final, skipped)
                    continue
                answer = Answer(
                    True, Reason.ACCEPTED, f"{cmd.name} accepted: {state.name} -> {final.name}"
                )
                trigger = Trigger.SKIP if skipped else Trigger.COMMAND
                accepted[state][cmd] = Accepted(
                    final,
                    skipped,
                    answer,
                    int(cmd),
                    trigger,
                    self.watch[cmd],
                    _entry_of(skipped, final),
                )
                refused[state][cmd] = (Reason.ACCEPTED, final, skipped)
        steps: list[ScStep | None] = [None] * NUM_STATES
        for state, nxt in table.state_complete.items():
            final, skipped = resolve(nxt, disabled, table.state_complete)
            trigger = Trigger.SKIP if skipped else Trigger.STATE_COMPLETE
            steps[state] = ScStep(
                final, skipped, trigger, final not in disabled, _entry_of(skipped, final)
            )
        for state, by_cmd in zip(State, accepted, strict=False):
            for key, a in by_cmd.items():
                by_cmd[key] = a._replace(run=self._run(state, number, a, steps))
        self.accepted[number] = accepted
        self.refused[number] = refused
        self.sc[number] = steps

    def _run(
        self, start: State, mode: int, accepted: Accepted, sc: list[ScStep | None]
    ) -> Run | None:
        """The :data:`Run` after the command ``accepted`` took the unit from ``start`` (in
        ``mode``) into its final state."""
        steps: list[RecordTail] = []
        between: list[State] = []
        first = state = accepted.final
        entry = accepted.entry
        while True:
            if state in self.timed:
                return None
            if state not in AT_ONCE_WITHOUT_EMS:
                break
            step = sc[state]
            if step is None or not step.enabled:
                return None
            if state is not first:
                between.append(state)
            steps.append((state, step.final, mode, mode, step.trigger, 0, "unit", step.skipped, ""))
            entry |= step.entry
            state = step.final
        if entry & Entry.STOP:
            return None
        tail = (
            start,
            accepted.final,
            mode,
            mode,
            accepted.trigger,
            accepted.cmd,
            OPERATOR,
            accepted.skipped,
            "",
        )
        return Run(
            start,
            mode,
            accepted.final,
            accepted.skipped,
            accepted.answer,
            accepted.cmd,
            accepted.trigger,
            tail,
            tuple(steps),
            tuple(between),
            state,
            entry,
        )

    # -- the table's verdict -----------------------------------------------------------------------
    def table_verdict(self, state: State, mode: int, cmd: int) -> Verdict:
        """The table alone (no guard): accepted, not allowed, unknown command, target disabled."""
        if not 1 <= cmd <= 10:
            return Verdict(Reason.UNKNOWN_COMMAND)
        reason, final, skipped = self.refused[mode][state][cmd]
        return Verdict(reason, final, skipped)

    def check(
        self, situation: Situation, state: State, mode: int, cmd: int, source: str
    ) -> Verdict:
        """The checked path: every guard in order around the table's verdict. (The engine's fast
        path accepts at once when the table does and no watched part is set.)"""
        if not 1 <= cmd <= 10:
            return Verdict(Reason.UNKNOWN_COMMAND)
        for g in self.before_table:
            if cmd in g.commands:
                detail = g.refuses(situation, cmd, source)
                if detail is not None:
                    return Verdict(g.reason, None, (), detail, g)
        verdict = self.table_verdict(state, mode, cmd)
        if verdict.reason is not Reason.ACCEPTED:
            return verdict
        for g in self.after_table:
            if cmd in g.commands:
                detail = g.refuses(situation, cmd, source)
                if detail is not None:
                    return Verdict(g.reason, verdict.final, verdict.skipped, detail, g)
        return verdict

    def refusal_text(
        self,
        verdict: Verdict,
        cmd: int,
        source: str,
        where: str,
        unit: str,
        mode_name: str,
        valid: Sequence[int],
    ) -> str:
        """The sentence of a refusal, ending with the commands valid now."""
        fields = {
            "command": command_name(cmd),
            "number": cmd,
            "source": source,
            "where": where,
            "unit": unit,
            "detail": verdict.detail,
            "mode": mode_name,
            "all": names_of(range(1, 11)),
        }
        if verdict.guard is not None:
            text = verdict.guard.sentence.format(**fields)
        else:
            if verdict.reason is Reason.STATE_DISABLED:
                fields["detail"] = verdict.final.name if verdict.final is not None else "its target"
            text = TABLE_SENTENCES.get(verdict.reason, TABLE_SENTENCES[Reason.COMMAND_NOT_ALLOWED])
            text = text.format(**fields)
        return f"{text} (valid now: {names_of(valid) or 'none'})"

    # -- questions of faces ------------------------------------------------------------------------
    def available_states(self, mode: int) -> frozenset[State]:
        """The states the unit can be in in ``mode`` (OPC UA AvailableStates): all but the
        disabled ones."""
        disabled: frozenset[State] = self.modes[mode].disabled
        return ALL_STATES - disabled

    def valid_commands(self, state: State, mode: int) -> tuple[Cmd, ...]:
        """Commands the table accepts in ``state`` and ``mode`` (no guard: alarms, missing EMs,
        interlocks, remote lock and mode changes in process may still refuse them); none in a
        state the mode disables (the unit is never there)."""
        if state in self.modes[mode].disabled:
            return ()
        return tuple(Cmd(c) for c in sorted(self.accepted[mode][state]))

    def target(self, state: State, mode: int, cmd: int) -> tuple[State, tuple[State, ...]] | None:
        """Where ``cmd`` takes the unit from ``state`` in ``mode`` (final state, skipped), or None
        when the table refuses it."""
        entry = self.accepted[mode][state].get(cmd) if 1 <= cmd <= 10 else None
        return None if entry is None else (entry.final, entry.skipped)

    def chain(self, first: State) -> tuple[State, ...]:
        """``first``, then on by State Complete up to the wait state (or Execute) it settles in:
        the states a command into ``first`` passes through (the model's; no mode)."""
        out = [first]
        sc = self.table.state_complete
        while out[-1] in sc and out[-1] is not S.EXECUTE:
            out.append(sc[out[-1]])
        return tuple(out)

    def reach(self, state: State, cmd: int) -> tuple[State, ...]:
        """Where ``cmd`` leads from ``state`` in the model: :meth:`chain` of its first state; ()
        when the table has no such transition."""
        first = self.table.commands.get((state, Cmd(cmd))) if 1 <= cmd <= 10 else None
        return () if first is None else self.chain(first)

    @staticmethod
    def settles_in(state: State) -> State:
        """The wait state (or Execute) the unit settles in from ``state`` when nothing
        intervenes: ``Status.StateRequested``."""
        return SETTLE.get(state, state)

    def command_target(self, cmd: int, mode: int | None = None) -> State | None:
        """The wait state (or Execute) a command leads to once its acting states completed
        (RESET -> IDLE, HOLD -> HELD, ...): the coordinator's target states. None when the
        command is accepted nowhere (in ``mode``, or in the model)."""
        targets: set[State]
        if mode is None:
            targets = {
                self.settles_in(to) for (_, c), to in self.table.commands.items() if c == cmd
            }
        else:
            targets = {self.settles_in(d[cmd].final) for d in self.accepted[mode] if cmd in d}
        return next(iter(targets)) if len(targets) == 1 else None

    def edges(self, mode: int | None = None) -> tuple[Edge, ...]:
        """The state diagram. Without ``mode``: the model's graph (every command edge of the table
        and every State Complete edge; the HMI greys disabled states). With ``mode``: the graph the
        unit runs in that mode — edges from enabled states, through skipped states to where they
        end, without refused ones (the target disabled)."""
        out: list[Edge] = []
        if mode is None:
            for (state, command), to in sorted(self.table.commands.items()):
                out.append(Edge(state, command, to))
            for state, to in sorted(self.table.state_complete.items()):
                out.append(Edge(state, None, to))
            return tuple(out)
        available = self.available_states(mode)
        for state in sorted(available):
            for cmd, entry in sorted(self.accepted[mode][state].items()):
                out.append(Edge(state, Cmd(cmd), entry.final, entry.skipped))
            step = self.sc[mode][state]
            if step is not None and step.enabled:
                out.append(Edge(state, None, step.final, step.skipped))
        return tuple(out)

    def available_transitions(self, mode: int, state: State | None = None) -> tuple[Edge, ...]:
        """Edges of :meth:`edges` (``mode``), from ``state`` only when given (OPC UA
        AvailableTransitions of the current state)."""
        return tuple(e for e in self.edges(mode) if state is None or e.from_state is state)

    def mode_change_refusal(self, current: int, target: int, state: State) -> str | None:
        """Why the change of mode ``current`` to ``target`` in ``state`` is refused, or None
        (unknown modes are refused too)."""
        a, b = self.modes.get(current), self.modes.get(target)
        if a is None or b is None:
            return f"mode {target if b is None else current} is not configured"
        return mode_change_refusal(a, b, state)


def _entry_of(skipped: tuple[State, ...], final: State) -> int:
    """The Entry flags of a transition, as a plain int (IntFlag operators run Python code)."""
    flags = 0
    for s in (*skipped, final):
        flags |= int(ENTRY.get(s, 0))
    return flags


#: id(config) -> its compiled rules, while the configuration lives (configurations are frozen
#: but hold dicts: not hashable, so no WeakKeyDictionary).
_compiled: dict[int, Rules] = {}


def rules_of(config: ConfigLike) -> Rules:
    """The compiled rules of a unit configuration (compiled once, then shared)."""
    key = id(config)
    rules = _compiled.get(key)
    if rules is None:
        timed = frozenset(config.timeouts) | frozenset(config.min_dwell)
        rules = Rules(config.table, config.modes, config.interlock_reaction, timed)
        _compiled[key] = rules
        weakref.finalize(config, _compiled.pop, key, None)
    return rules


__all__ = [
    "ABORT_EXCEPT",
    "AGGREGATING",
    "AT_ONCE_WITHOUT_EMS",
    "BLOCKED_BY_REACTION",
    "CALLER_KINDS",
    "COMMANDS_2022",
    "DEFAULT_REACTIONS",
    "ENTRY",
    "EXCUSE_OFFLINE",
    "FAULT_COMMANDS",
    "GUARDS",
    "IMPLIED_DISABLED",
    "LOCAL_KINDS",
    "LOCKED_INPUTS",
    "MAX_EMS",
    "MOTION",
    "ONLY_WITH_ACTIVE_EMS",
    "PRIORITY",
    "REACTIONS",
    "SETTLE",
    "SOURCE_KINDS",
    "STATE_COMPLETE",
    "STOP_EXCEPT",
    "Accepted",
    "Alert",
    "Edge",
    "Entry",
    "Guard",
    "RecordTail",
    "Rules",
    "Run",
    "ScStep",
    "SourceKind",
    "TransitionTable",
    "Trigger",
    "Verdict",
    "Watch",
    "build_table",
    "is_remote",
    "lock_change_refusal",
    "locked_refusal",
    "mode_change_refusal",
    "override_refusal",
    "registration_refusal",
    "remote_locked",
    "resolve",
    "rules_of",
    "source_of",
    "source_refusal",
]
