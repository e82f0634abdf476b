"""Unit modes as configured: each mode's corrected set of disabled states and the states mode
changes are allowed in, and the three standard modes' defaults.

A :class:`ModeDef` is one mode's configuration after the implication rules of docs/packml.md §3
(:data:`.rules.IMPLIED_DISABLED`) have been applied; the rules that read it (skip-through, the
mode-change matrix) are in :mod:`.rules`.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from .numbers import MANDATORY, WAIT, Mode, State
from .rules import corrected_disabled

S = State

#: Groups a configuration may name instead of single states (e.g. ``disabled_states: [hold]``).
GROUPS: Mapping[str, frozenset[State]] = {
    "HOLD": frozenset({S.HOLDING, S.HELD, S.UNHOLDING}),
    "SUSPEND": frozenset({S.SUSPENDING, S.SUSPENDED, S.UNSUSPENDING}),
    "COMPLETE_GROUP": frozenset({S.COMPLETING, S.COMPLETE}),
}


@dataclass(frozen=True)
class ModeDef:
    """One unit mode. ``disabled`` is the corrected set (implications applied)."""

    number: int
    name: str
    disabled: frozenset[State]
    change_allowed: frozenset[State]

    @property
    def disabled_mask(self) -> int:
        """``Admin.StatesDisabled``: bit n = state n."""
        mask = 0
        for s in self.disabled:
            mask |= 1 << int(s)
        return mask


def make_mode(
    number: int, name: str, disabled: Iterable[State] = (), change_allowed: Iterable[State] = ()
) -> ModeDef:
    disabled_set = corrected_disabled(disabled)
    bad = disabled_set & MANDATORY
    if bad:
        raise ValueError(f"{', '.join(s.name for s in sorted(bad))} can never be disabled")
    allowed = frozenset(change_allowed)
    not_wait = allowed - WAIT
    if not_wait:
        names = ", ".join(s.name for s in sorted(not_wait))
        raise ValueError(f"mode changes can only be allowed in wait states, not in {names}")
    return ModeDef(number, name, disabled_set, allowed)


def default_modes() -> dict[int, ModeDef]:
    """Production (full model), Maintenance (Suspend group off), Manual (Hold, Suspend, Complete off)."""
    change = (S.STOPPED, S.IDLE, S.ABORTED)
    return {
        Mode.PRODUCTION: make_mode(1, "PRODUCTION", (), change),
        Mode.MAINTENANCE: make_mode(2, "MAINTENANCE", GROUPS["SUSPEND"], change),
        Mode.MANUAL: make_mode(
            3,
            "MANUAL",
            GROUPS["HOLD"] | GROUPS["SUSPEND"] | GROUPS["COMPLETE_GROUP"],
            change,
        ),
    }
