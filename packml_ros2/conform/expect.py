"""What the standard expects of a target, from the rule book (:mod:`packml_ros2.core.rules`)
compiled for the model the target declares: a command's verdict and the states it shows on
its way, a mode change's verdict, and the shortest way from one state to another.

Nothing of the rules is written here again: :class:`~packml_ros2.core.rules.Rules` answers
(its compiled tables ``accepted``, ``refused`` and ``sc``); this module follows them.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass

from ..core.numbers import ACTING, WAIT, Cmd, State
from ..core.reasons import Reason
from ..core.rules import COMMANDS, Rules

S = State
#: The states a command settles in: the wait states and Execute (where production settles).
RESTING: frozenset[State] = WAIT | {S.EXECUTE}
#: The order wait states are visited in (a machine's usual round first).
VISIT_ORDER: tuple[State, ...] = (
    S.STOPPED,
    S.IDLE,
    S.EXECUTE,
    S.HELD,
    S.SUSPENDED,
    S.COMPLETE,
    S.ABORTED,
)
#: The commands a route prefers, in order (an Abort only where nothing else leads).
ROUTE_PREFERENCE: tuple[Cmd, ...] = (
    Cmd.RESET,
    Cmd.START,
    Cmd.STOP,
    Cmd.CLEAR,
    Cmd.UNHOLD,
    Cmd.UNSUSPEND,
    Cmd.HOLD,
    Cmd.SUSPEND,
    Cmd.COMPLETE,
    Cmd.ABORT,
)


@dataclass(frozen=True)
class Expect:
    """A command's verdict: accepted (``reason`` ACCEPTED) with the states it shows on its way
    (``shown``, ending where it settles) and the disabled states it passes through
    (``skipped``); or refused with ``reason`` (nothing shown)."""

    reason: Reason
    shown: tuple[State, ...] = ()
    skipped: tuple[State, ...] = ()

    @property
    def accepted(self) -> bool:
        return self.reason is Reason.ACCEPTED

    @property
    def settle(self) -> State | None:
        return self.shown[-1] if self.shown else None


def command(rules: Rules, mode: int, state: State, cmd: int) -> Expect:
    """The verdict of ``cmd`` in ``state`` and ``mode`` without guards (no alarm, no EM
    missing, local source): the table's."""
    verdict = rules.table_verdict(state, mode, cmd)
    if verdict.reason is not Reason.ACCEPTED or verdict.final is None:
        return Expect(verdict.reason)
    shown, skipped = follow(rules, mode, verdict.final)
    return Expect(Reason.ACCEPTED, shown, (*verdict.skipped, *skipped))


def follow(rules: Rules, mode: int, first: State) -> tuple[tuple[State, ...], tuple[State, ...]]:
    """``first``, then on by State Complete (skipping disabled states) up to the state that
    waits: (the states shown, the states skipped)."""
    shown: list[State] = [first]
    skipped: list[State] = []
    steps = rules.sc[mode]
    state = first
    while state in ACTING and state is not S.EXECUTE:
        step = steps[state]
        if step is None or not step.enabled:
            break  # State Complete is ignored here: the unit stays
        skipped.extend(step.skipped)
        state = step.final
        shown.append(state)
    return tuple(shown), tuple(skipped)


def mode_change(rules: Rules, current: int, target: int, state: State) -> str | None:
    """Why a change of mode ``current`` to ``target`` in ``state`` is refused, or None."""
    return rules.mode_change_refusal(current, target, state)


def settles_from(rules: Rules, mode: int, state: State) -> State:
    """Where a target in ``state`` comes to rest by itself (an acting state completes)."""
    return follow(rules, mode, state)[0][-1] if state in ACTING else state


def route(
    rules: Rules,
    mode: int,
    start: State,
    goals: Iterable[State],
    avoid: frozenset[tuple[State, int]] = frozenset(),
    stuck: bool = False,
) -> tuple[tuple[int, State], ...] | None:
    """The fewest commands that take a target in ``start`` (``mode``) to one of ``goals``: each
    command with the state it settles in; () when already there; None when no way leads there.
    ``avoid``: (state, command) pairs not to use (the target misbehaved on them); ``stuck``: the
    target in the acting state ``start`` does not complete it (only a command leads on)."""
    wanted = frozenset(goals)
    first = settles_from(rules, mode, start) if start not in wanted and not stuck else start
    if first in wanted:
        return ()
    # from an acting state only the commands valid in it (Stop, Abort) lead on before it settles
    origin = start if start in ACTING and start is not S.EXECUTE else first
    seen = {origin}
    queue: deque[tuple[State, tuple[tuple[int, State], ...]]] = deque([(origin, ())])
    while queue:
        here, path = queue.popleft()
        for cmd in ROUTE_PREFERENCE:
            if (here, int(cmd)) in avoid:
                continue
            outcome = command(rules, mode, here, cmd)
            if not outcome.accepted or outcome.settle is None:
                continue
            there = outcome.settle
            if there in seen:
                continue
            step = (*path, (int(cmd), there))
            if there in wanted:
                return step
            seen.add(there)
            queue.append((there, step))
    return None


def reachable(rules: Rules, mode: int) -> tuple[State, ...]:
    """The resting states a target can be brought to in ``mode``, in :data:`VISIT_ORDER`."""
    available = rules.available_states(mode)
    return tuple(
        s for s in VISIT_ORDER if s in available and route(rules, mode, S.STOPPED, [s]) is not None
    )


__all__ = [
    "COMMANDS",
    "RESTING",
    "VISIT_ORDER",
    "Expect",
    "command",
    "follow",
    "mode_change",
    "reachable",
    "route",
    "settles_from",
]
