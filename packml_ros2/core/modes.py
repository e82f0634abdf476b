"""Unit modes: disabled states, skip-through of disabled acting states, the mode-change matrix.

A :class:`ModeDef` is one mode's configuration after the implication rules of PACKML.md section 3
have been applied; :func:`resolve` walks a command or State Complete through disabled acting states.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from .numbers import ACTING, MANDATORY, WAIT, Mode, State

S = State

#: Disabling a wait state disables the acting states that only serve it.
IMPLIED_DISABLED: Mapping[State, frozenset[State]] = {
    S.HELD: frozenset({S.HOLDING, S.UNHOLDING}),
    S.SUSPENDED: frozenset({S.SUSPENDING, S.UNSUSPENDING}),
    S.COMPLETE: frozenset({S.COMPLETING}),
}
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


def corrected_disabled(states: Iterable[State]) -> frozenset[State]:
    """Apply the implication rules. Mandatory states are the caller's to refuse (config errors)."""
    out = set(states)
    for wait, implied in IMPLIED_DISABLED.items():
        if wait in out:
            out |= implied
    return frozenset(out)


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


def resolve(
    first: State, disabled: frozenset[State], state_complete: Mapping[State, State]
) -> tuple[State, tuple[State, ...]]:
    """Where the unit ends up when it is sent to ``first``: disabled acting states are passed
    through to their State Complete successor. Returns (final state, skipped states). The final
    state may be a disabled wait state; the caller refuses that."""
    skipped: list[State] = []
    state = first
    while state in disabled and state in ACTING:
        skipped.append(state)
        state = state_complete[state]
    return state, tuple(skipped)


def mode_change_refusal(current: ModeDef, target: ModeDef, state: State) -> str | None:
    """Why a change from ``current`` to ``target`` in ``state`` is not allowed, or None."""
    if state not in current.change_allowed:
        allowed = ", ".join(s.name for s in sorted(current.change_allowed)) or "no state"
        return f"{current.name} allows mode changes only in {allowed}"
    if state not in target.change_allowed:
        allowed = ", ".join(s.name for s in sorted(target.change_allowed)) or "no state"
        return f"{target.name} allows mode changes only in {allowed}"
    if state in target.disabled:
        return f"{state.name} is disabled in {target.name}"
    return None
