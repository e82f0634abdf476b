"""The cases of a conformance run, per profile, from the model a target declares.

- ``core``: every resting state (the wait states and Execute) the first mode reaches × every
  command 1..10: accepted or refused as the standard says, the states shown on the way, where
  it settles, how long it took, the Status tags after it;
- ``modes``: the mode-change matrix (every resting state of every mode × every other mode),
  then the core's checks in every other mode (their disabled states: skip-through, refusals);
- ``packtags``: the Admin times (StateCurrentTime, ModeCurrentTime growing, StateCumulativeTime
  and ModeCumulativeTime accumulating over stays) and the counters' reset;
- ``all``: all of them.

:func:`order` then sets the order a run takes: each profile's cases keep their place, but the
checks of commands in one mode run as a tour, so that a check's own transition is the way to the
next check wherever it can be, not a detour (the demo cell's core profile: 27 commands of travel
instead of 51).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cache

from ..core.numbers import Cmd, State, command_name
from ..core.rules import COMMANDS, Rules
from . import expect

PROFILES: dict[str, tuple[str, ...]] = {
    "core": ("core",),
    "modes": ("modes",),
    "packtags": ("packtags",),
    "all": ("core", "modes", "packtags"),
}
#: The PackTag checks of the packtags profile, in the order they run (each builds on the one
#: before: the state's stay goes on).
PACKTAG_CHECKS: tuple[tuple[str, str], ...] = (
    ("state-current-time", "StateCurrentTime grows while the target stays in a state"),
    ("mode-current-time", "ModeCurrentTime grows while the target stays in a mode"),
    ("mode-cumulative-time", "ModeCumulativeTime grows with the mode's current stay"),
    ("state-cumulative-time", "StateCumulativeTime keeps a state's earlier stays"),
    ("counters-reset", "a counter reset sets every Count to 0 and keeps AccCount"),
)


@dataclass(frozen=True)
class Case:
    """One check. ``kind``: "command" (``cmd`` in ``state`` and ``mode``), "mode" (a change to
    ``to_mode`` in ``state`` and ``mode``) or "packtag" (``check``, one of
    :data:`PACKTAG_CHECKS`, in ``state`` and ``mode``)."""

    group: str
    kind: str
    mode: int
    state: State
    cmd: int = 0
    to_mode: int = 0
    check: str = ""

    def name(self, mode_name: dict[int, str]) -> str:
        """For people and for JUnit: ``PRODUCTION IDLE START``."""
        where = f"{mode_name.get(self.mode, self.mode)} {self.state.name}"
        if self.kind == "command":
            return f"{where} {command_name(self.cmd)}"
        if self.kind == "mode":
            return f"{where} -> {mode_name.get(self.to_mode, self.to_mode)}"
        return f"{self.check} ({where})"


def command_cases(rules: Rules, group: str, mode: int) -> list[Case]:
    """Every resting state of ``mode`` × every command."""
    return [
        Case(group, "command", mode, state, cmd=int(cmd))
        for state in expect.reachable(rules, mode)
        for cmd in COMMANDS
    ]


def mode_cases(rules: Rules, modes: Sequence[int]) -> list[Case]:
    """The mode-change matrix: every resting state of every mode × every other mode."""
    return [
        Case("modes", "mode", a, state, to_mode=b)
        for a in modes
        for state in expect.reachable(rules, a)
        for b in modes
        if b != a
    ]


def packtag_cases(mode: int) -> list[Case]:
    return [Case("packtags", "packtag", mode, State.IDLE, check=name) for name, _ in PACKTAG_CHECKS]


def groups_of(profile: str) -> tuple[str, ...]:
    """The groups of a profile, or of several (``core,packtags``), in their order."""
    names = [p.strip() for p in profile.split(",") if p.strip()]
    unknown = [p for p in names if p not in PROFILES]
    if unknown or not names:
        raise ValueError(
            f"profile must be one of {', '.join(PROFILES)} (or several, comma-separated), "
            f"not {profile!r}"
        )
    wanted = {g for p in names for g in PROFILES[p]}
    return tuple(g for g in PROFILES["all"] if g in wanted)


def plan(rules: Rules, profile: str, modes: Sequence[int]) -> list[Case]:
    """The cases of ``profile`` over ``modes`` (the first is the core's mode)."""
    first, others = modes[0], list(modes[1:])
    cases: list[Case] = []
    for group in groups_of(profile):
        if group == "core":
            cases += command_cases(rules, "core", first)
        elif group == "modes":  # the matrix first: it needs no state the other modes reach
            cases += mode_cases(rules, modes)
            for mode in others:
                cases += command_cases(rules, "modes", mode)
        else:
            cases += packtag_cases(first)
    return cases


def order(rules: Rules, cases: Sequence[Case], mode: int | None, state: State | None) -> list[Case]:
    """``cases`` in the order a run takes them from ``state`` in ``mode`` (where the target was
    found; None: unknown). Each run of command checks in one group and mode becomes a tour:
    at each resting state first the checks of commands the standard refuses there (nothing
    moves), then the accepted command whose landing leaves the least travel for the rest (by
    a greedy completion, counted in commands); where no check is left, on to the nearest state
    that has one. Every other case keeps its place: the mode matrix and the PackTag checks
    build on their order."""
    out: list[Case] = []
    i = 0
    while i < len(cases):
        case = cases[i]
        if case.kind != "command":
            out.append(case)
            mode, state = _after(rules, case)
            i += 1
            continue
        j = i
        while j < len(cases) and (cases[j].kind, cases[j].group, cases[j].mode) == (
            "command",
            case.group,
            case.mode,
        ):
            j += 1
        start = (
            expect.settles_from(rules, mode, state)
            if mode == case.mode and state is not None
            else case.state
        )
        tour = _Tour(rules, case.mode)
        block = tour.rollout(start, cases[i:j])
        out += block
        mode, state = case.mode, tour.land(block[-1])
        i = j
    return out


def _after(rules: Rules, case: Case) -> tuple[int | None, State | None]:
    """Where a target is after a case that is not a command check (None: not known)."""
    if case.kind == "mode":
        accepted = expect.mode_change(rules, case.mode, case.to_mode, case.state) is None
        return (case.to_mode if accepted else case.mode), case.state
    return None, None


class _Tour:
    """The order of the command checks of one mode (see :func:`order`)."""

    def __init__(self, rules: Rules, mode: int) -> None:
        self.rules, self.mode = rules, mode
        self.dist: Callable[[State, State], float] = cache(self._dist)
        self.land: Callable[[Case], State] = cache(self._land)  # (asked again in every rollout)

    def _dist(self, a: State, b: State) -> float:
        way = expect.route(self.rules, self.mode, a, [b])
        return float("inf") if way is None else len(way)

    def _land(self, case: Case) -> State:
        """Where the case's command leaves the target (refused: where it was)."""
        settle = expect.command(self.rules, self.mode, case.state, case.cmd).settle
        return case.state if settle is None else settle

    def travel(self, start: State, cases: Sequence[Case]) -> float:
        """The commands of travel between the checks of ``cases`` in this order."""
        total, here = 0.0, start
        for case in cases:
            total += self.dist(here, case.state)
            here = self.land(case)
        return total

    def greedy(self, start: State, cases: Sequence[Case]) -> list[Case]:
        return self._walk(start, cases, self._nearest_after)

    def rollout(self, start: State, cases: Sequence[Case]) -> list[Case]:
        return self._walk(start, cases, self._least_travel_after)

    def _nearest_after(self, case: Case, rest: list[Case]) -> float:
        there = self.land(case)
        return min((self.dist(there, c.state) for c in rest), default=0.0)

    def _least_travel_after(self, case: Case, rest: list[Case]) -> float:
        there = self.land(case)
        return self.travel(there, self.greedy(there, rest))

    def _walk(
        self, start: State, cases: Sequence[Case], cost: Callable[[Case, list[Case]], float]
    ) -> list[Case]:
        pending, out, here = list(cases), [], start
        while pending:
            at_hand = [c for c in pending if c.state == here]
            if not at_hand:  # on to the nearest state with a check (first in plan order)
                here = min((c.state for c in pending), key=lambda s: self.dist(here, s))
                continue
            staying = [c for c in at_hand if self.land(c) == here]
            if staying:
                pick = staying[0]
            else:
                pick = min(at_hand, key=lambda c: cost(c, [p for p in pending if p is not c]))
            out.append(pick)
            pending.remove(pick)
            here = self.land(pick)
        return out


def describe(case: Case, rules: Rules, mode_name: dict[int, str]) -> str:
    """What the standard expects of ``case``, for ``--dry`` and the report."""
    if case.kind == "command":
        outcome = expect.command(rules, case.mode, case.state, case.cmd)
        if outcome.accepted:
            way = " -> ".join(s.name for s in outcome.shown)
            return f"accepted: {way}"
        return f"refused ({outcome.reason.name})"
    if case.kind == "mode":
        why = expect.mode_change(rules, case.mode, case.to_mode, case.state)
        return "accepted" if why is None else f"refused ({why})"
    return dict(PACKTAG_CHECKS)[case.check]


__all__ = ["PACKTAG_CHECKS", "PROFILES", "Case", "Cmd", "describe", "groups_of", "order", "plan"]
