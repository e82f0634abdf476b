"""Shared helpers of the engine tests: a settable clock, docs/packml.md sections 1-3 encoded as data
independently of ``packml_ros2.core.transitions``/``modes``, and a walker that drives a unit into a
state legitimately (by commands and State Complete reports along a path of the spec's graph).

Only the number enums (``State``, ``Cmd``, ``Reason``) are taken from the engine; test_conformance
checks their numbers against docs/packml.md §1.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from packml_ros2.core import Cmd, Reason, State, Unit, parse_cell

S, C = State, Cmd


class FakeClock:
    """A settable clock: ``clock.t`` seconds; ``clock.advance(dt)``."""

    def __init__(self, t: float = 1_000.0) -> None:
        self.t = float(t)

    def __call__(self) -> float:
        return self.t

    def advance(self, dt: float) -> float:
        self.t += dt
        return self.t


# -- docs/packml.md §1 -----------------------------------------------------------------------------
#: name -> number, as printed in docs/packml.md §1.
SPEC_STATE_NUMBERS = {
    "UNDEFINED": 0, "CLEARING": 1, "STOPPED": 2, "STARTING": 3, "IDLE": 4, "SUSPENDED": 5,
    "EXECUTE": 6, "STOPPING": 7, "ABORTING": 8, "ABORTED": 9, "HOLDING": 10, "HELD": 11,
    "UNHOLDING": 12, "SUSPENDING": 13, "UNSUSPENDING": 14, "RESETTING": 15, "COMPLETING": 16,
    "COMPLETE": 17,
}  # fmt: skip
SPEC_COMMAND_NUMBERS = {
    "UNDEFINED": 0, "RESET": 1, "START": 2, "STOP": 3, "HOLD": 4, "UNHOLD": 5, "SUSPEND": 6,
    "UNSUSPEND": 7, "ABORT": 8, "CLEAR": 9, "COMPLETE": 10,
}  # fmt: skip
SPEC_MODE_NUMBERS = {"INVALID": 0, "PRODUCTION": 1, "MAINTENANCE": 2, "MANUAL": 3}

ALL_STATES = frozenset(s for s in State if s is not S.UNDEFINED)
SPEC_ACTING = frozenset(
    {S.CLEARING, S.STARTING, S.EXECUTE, S.STOPPING, S.ABORTING, S.HOLDING, S.UNHOLDING,
     S.SUSPENDING, S.UNSUSPENDING, S.RESETTING, S.COMPLETING}
)  # fmt: skip
SPEC_WAIT = frozenset({S.STOPPED, S.IDLE, S.SUSPENDED, S.HELD, S.COMPLETE, S.ABORTED})
MANDATORY = frozenset({S.STOPPED, S.IDLE, S.EXECUTE, S.ABORTED})
#: Every command number, plus numbers outside the model.
COMMANDS = tuple(range(11))
BAD_COMMANDS = (11, 42, -1)
#: Commands that start motion (refused while an active EM is offline or a reacting alarm is active).
MOTION = frozenset({C.RESET, C.START, C.UNHOLD, C.UNSUSPEND})

# -- docs/packml.md §2, the TR88-2022 table --------------------------------------------------------
SPEC_COMMAND_TABLE: Mapping[tuple[State, Cmd], State] = {
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
SPEC_SC_TABLE: Mapping[State, State] = {
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
STOP_FROM = ALL_STATES - {S.STOPPING, S.STOPPED, S.ABORTING, S.ABORTED, S.CLEARING}
ABORT_FROM = ALL_STATES - {S.ABORTING, S.ABORTED}

# -- docs/packml.md §3 -----------------------------------------------------------------------------
IMPLIES = {
    S.HELD: {S.HOLDING, S.UNHOLDING},
    S.SUSPENDED: {S.SUSPENDING, S.UNSUSPENDING},
    S.COMPLETE: {S.COMPLETING},
}
HOLD_GROUP = {S.HOLDING, S.HELD, S.UNHOLDING}
SUSPEND_GROUP = {S.SUSPENDING, S.SUSPENDED, S.UNSUSPENDING}
COMPLETE_GROUP = {S.COMPLETING, S.COMPLETE}
DEFAULT_CHANGE = frozenset({S.STOPPED, S.IDLE, S.ABORTED})


@dataclass(frozen=True)
class SpecMode:
    number: int
    name: str
    disabled: frozenset[State]
    change_allowed: frozenset[State]


def corrected(disabled: Iterable[State]) -> frozenset[State]:
    out = set(disabled)
    for wait, acting in IMPLIES.items():
        if wait in out:
            out |= acting
    return frozenset(out)


def spec_mode(
    number: int, name: str, disabled: Iterable[State] = (), change: Iterable[State] = DEFAULT_CHANGE
) -> SpecMode:
    return SpecMode(number, name.upper(), corrected(disabled), frozenset(change))


DEFAULT_SPEC_MODES = {
    1: spec_mode(1, "PRODUCTION"),
    2: spec_mode(2, "MAINTENANCE", SUSPEND_GROUP),
    3: spec_mode(3, "MANUAL", HOLD_GROUP | SUSPEND_GROUP | COMPLETE_GROUP),
}


@dataclass
class Spec:
    """The decided behaviour of docs/packml.md sections 2-3 for one configuration."""

    model: str = "2022"
    hold_from: frozenset[State] | None = None
    complete_from: frozenset[State] | None = None
    modes: dict[int, SpecMode] = field(default_factory=lambda: dict(DEFAULT_SPEC_MODES))

    def target(self, state: State, cmd: int) -> State | None:
        """Where command ``cmd`` leads from ``state`` in the table, or None."""
        if cmd == C.STOP:
            return S.STOPPING if state in STOP_FROM else None
        if cmd == C.ABORT:
            return S.ABORTING if state in ABORT_FROM else None
        if cmd == C.HOLD:
            hold = self.hold_from
            if hold is None:
                hold = frozenset({S.EXECUTE} if self.model == "2015" else {S.EXECUTE, S.SUSPENDED})
            return S.HOLDING if state in hold else None
        if cmd == C.COMPLETE:
            comp = self.complete_from
            if comp is None:
                comp = frozenset(
                    {S.EXECUTE} if self.model == "2015" else {S.EXECUTE, S.HELD, S.SUSPENDED}
                )
            return S.COMPLETING if state in comp else None
        if not 1 <= cmd <= 10:
            return None
        return SPEC_COMMAND_TABLE.get((state, Cmd(cmd)))

    def resolve(self, first: State, mode: int) -> tuple[State, tuple[State, ...]]:
        """Skip-through of disabled acting states (section 3)."""
        disabled = self.modes[mode].disabled
        skipped: list[State] = []
        state = first
        while state in SPEC_ACTING and state in disabled:
            skipped.append(state)
            state = SPEC_SC_TABLE[state]
        return state, tuple(skipped)

    def command(self, state: State, cmd: int, mode: int) -> tuple[Reason, State | None, tuple]:
        """(reason, final state, skipped states) of ``cmd`` in ``state`` and ``mode``."""
        if not 1 <= cmd <= 10:
            return Reason.UNKNOWN_COMMAND, None, ()
        first = self.target(state, cmd)
        if first is None:
            return Reason.COMMAND_NOT_ALLOWED, None, ()
        final, skipped = self.resolve(first, mode)
        if final in self.modes[mode].disabled:
            return Reason.STATE_DISABLED, final, skipped
        return Reason.ACCEPTED, final, skipped

    def state_complete(self, state: State, mode: int) -> tuple[State, tuple[State, ...]] | None:
        """Where SC leads from an acting state (None for wait states); the final state may be
        disabled (then SC is ignored)."""
        if state not in SPEC_ACTING:
            return None
        return self.resolve(SPEC_SC_TABLE[state], mode)

    def valid(self, state: State, mode: int) -> list[Cmd]:
        return [Cmd(c) for c in range(1, 11) if self.command(state, c, mode)[0] is Reason.ACCEPTED]

    def edges(self, state: State, mode: int) -> list[tuple[tuple[Any, ...], State]]:
        """Every way out of ``state``: (("cmd", c), to) and (("sc",), to)."""
        out: list[tuple[tuple[Any, ...], State]] = []
        for c in range(1, 11):
            reason, final, _ = self.command(state, c, mode)
            if reason is Reason.ACCEPTED and final is not None:
                out.append((("cmd", Cmd(c)), final))
        sc = self.state_complete(state, mode)
        if sc is not None and sc[0] not in self.modes[mode].disabled:
            out.append((("sc",), sc[0]))
        return out

    def reachable(self, mode: int, start: State = S.STOPPED) -> dict[State, list[tuple[Any, ...]]]:
        """Every state reachable in ``mode`` from ``start`` with a shortest path of actions."""
        paths: dict[State, list[tuple[Any, ...]]] = {start: []}
        queue = deque([start])
        while queue:
            s = queue.popleft()
            for action, to in self.edges(s, mode):
                if to not in paths:
                    paths[to] = [*paths[s], action]
                    queue.append(to)
        return paths

    def settle(self, state: State, mode: int) -> State:
        """Where a unit without active EMs comes to rest: SC is immediate except in Execute."""
        while state in SPEC_ACTING and state is not S.EXECUTE:
            sc = self.state_complete(state, mode)
            assert sc is not None
            if sc[0] in self.modes[mode].disabled:
                return state
            state = sc[0]
        return state


def valid_text(cmds: Iterable[int]) -> str:
    return ", ".join(Cmd(c).name for c in cmds) or "none"


# -- building units --------------------------------------------------------------------------------------
def cell_unit(unit: Mapping[str, Any], name: str = "u") -> Any:
    """A UnitConfig from a YAML-like mapping of ``units.<name>``."""
    doc = {"cell": "test_cell", "units": {name: {"persistence": False, **unit}}}
    return parse_cell(doc).units[name]


def drive(unit: Unit, path: Iterable[tuple[Any, ...]], em: str = "em1") -> None:
    """Walk ``path`` (("cmd", c) or ("sc",)) on ``unit``; every step must be accepted."""
    for action in path:
        if action[0] == "cmd":
            answer = unit.command(action[1])
        else:
            answer = unit.em_complete(em, unit.state, unit.sequence)
        assert answer.accepted, (action, answer)


def transitions(unit: Unit) -> list[Any]:
    """The transition records drained from ``unit``."""
    return [x for kind, x in unit.drain() if kind == "transition"]
