"""The cases of a conformance run, per profile, from the model a target declares.

- ``core``: every resting state (the wait states and Execute) the first mode reaches × every
  command 1..10: accepted or refused as the standard says, the states shown on the way, where
  it settles, how long it took, the Status tags after it;
- ``modes``: the mode-change matrix (every resting state of every mode × every other mode),
  then the core's checks in every other mode (their disabled states: skip-through, refusals);
- ``packtags``: the Admin times (StateCurrentTime, ModeCurrentTime growing, StateCumulativeTime
  and ModeCumulativeTime accumulating over stays) and the counters' reset;
- ``all``: all of them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

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


__all__ = ["PACKTAG_CHECKS", "PROFILES", "Case", "Cmd", "describe", "groups_of", "plan"]
