"""Line interlocks (docs/packml.md §4): Blocked/Starved from the unit's EMs and interlocks set from
outside (the coordinator) suspend the unit while it is in Execute and unsuspend it when all are
cleared, if the unit was suspended by one (``interlock_reaction: suspend``; the rule:
:data:`.rules.INTERLOCK_SUSPEND`, :data:`.rules.INTERLOCK_RESUME`).

:class:`Interlocks` owns the active interlocks, whether the unit's suspension is theirs, and which
(state, sequence) it last acted in (one attempt per state entry). It keeps the ``INTERLOCK`` bit of
the unit's :class:`~.rules.Alert`.

The transitions an interlock causes name whose interlock it is in their source,
``interlock:<holder>`` (:func:`interlock_source`): ``interlock:em:<name>`` when the unit's own EM
reports Blocked/Starved, ``interlock:<source>`` when ``<source>`` set it from outside
(``interlock:coordinator``: propagated by the cell coordinator from a neighbour). Suspend names
the interlock that caused it, Unsuspend the one whose clearing released the unit.
"""

from __future__ import annotations

from collections.abc import Collection

from .numbers import Cmd, State
from .reasons import Answer, Reason
from .rules import INTERLOCK_RESUME, INTERLOCK_SUSPEND, Alert, Watch, locked_refusal

#: OMAC stop-reason IDs (Beckhoff E_AlarmID ranges) of interlock stops.
STOP_ID_BLOCKED = 3002  # downstream: discharge blocked
STOP_ID_STARVED = 2499  # upstream: undefined upstream reason
#: Interlocks set from outside (``set_interlock``) a unit holds at most: one per source.
MAX_EXTERNAL = 16
#: Keys of :attr:`Interlocks.active`: ``em:<name>`` (the unit's own EM), ``ext:<source>`` (set from
#: outside by ``source``).
EXTERNAL_KEY = "ext:"
#: The source kind of the transitions an interlock causes (rules.SOURCE_KINDS: local).
INTERLOCK_KIND = "interlock"
#: The source of interlock transitions in input logs of schema 1 and before (one for all).
LEGACY_SOURCE = INTERLOCK_KIND


def interlock_source(key: str) -> str:
    """The source of a transition caused by the interlock ``key``: ``interlock:em:<name>`` for the
    unit's own EM, ``interlock:<source>`` for one set from outside by ``source``."""
    holder = key[len(EXTERNAL_KEY) :] if key.startswith(EXTERNAL_KEY) else key
    return f"{INTERLOCK_KIND}:{holder}" if holder else INTERLOCK_KIND


def external_refusal(held: Collection[str], active: bool, source: str, unit: str) -> Answer | None:
    """Why ``set_interlock`` from ``source`` is refused, ``held``: the sources whose interlocks
    the unit holds (None: it is taken). Each source holds one interlock and clears only its own;
    a unit holds at most :data:`MAX_EXTERNAL`."""
    if active:
        if source not in held and len(held) >= MAX_EXTERNAL:
            return Answer.no(
                Reason.INVALID_ARGUMENT,
                f"interlock from {source} refused: {unit} holds {MAX_EXTERNAL} interlocks from "
                "outside already (one per source)",
            )
        return None
    if source not in held:
        still = f" (held by {', '.join(sorted(held))})" if held else ""
        return Answer.no(
            Reason.NOTHING_TO_DO,
            f"nothing cleared: {unit} holds no interlock from {source}{still}; each source clears "
            "only its own",
        )
    return None


def interlock_refusal(
    held: Collection[str], active: bool, source: str, remote_enabled: bool, unit: str
) -> Answer | None:
    """Why ``set_interlock`` from ``source`` is refused, by a unit and a PLC bridge alike (None:
    it is taken). The remote lock guards *setting* one; *clearing* never asks for anything: a
    source releases its own hold (the coordinator, once downstream is free again, even after the
    operator switched the unit to local: else a hold nobody at the machine may clear would keep
    the unit suspended), and clearing what it does not hold is NOTHING_TO_DO."""
    if active:
        locked = locked_refusal("interlock", source, remote_enabled, unit)
        if locked is not None:
            return locked
    return external_refusal(held, active, source, unit)


class Interlocks:
    __slots__ = ("active", "alert", "attempt", "busy", "released", "suspended")

    def __init__(self, alert: Alert) -> None:
        self.alert = alert
        self.active: dict[str, tuple[str, int]] = {}  #: key -> (reason, stop-reason ID)
        self.suspended = False  #: the unit is in Suspending/Suspended because of an interlock
        self.attempt: tuple[int, int] = (-1, -1)  #: (state, sequence) of the last action
        self.busy = False  #: an interlock is active or holds the suspension: the unit must look
        self.released = ""  #: the key of the interlock cleared last (the Unsuspend's holder)

    def __bool__(self) -> bool:
        return bool(self.active)

    def set(self, key: str, reason: str, stop_id: int) -> None:
        self.active[key] = (reason, stop_id)
        self.alert.set(Watch.INTERLOCK, True)
        self.busy = True

    def clear(self, key: str) -> None:
        if self.active.pop(key, None) is not None:
            self.released = key
        self.alert.set(Watch.INTERLOCK, bool(self.active))
        self.busy = bool(self.active) or self.suspended

    def reasons(self) -> list[str]:
        return [reason for reason, _ in self.active.values()]

    def says(self, word: str) -> bool:
        """Whether an interlock's reason contains ``word`` (``blocked``/``starved``)."""
        return any(word in reason for reason, _ in self.active.values())

    def action(self, state: State, sequence: int) -> tuple[Cmd, str, int, str] | None:
        """The command an interlock asks for now, once per (state, sequence): Suspend in Execute
        while one is active, Unsuspend in Suspended once all are cleared (if they suspended
        the unit). (command, detail, stop-reason ID, the interlock's key) or None."""
        at = (int(state), sequence)
        if self.attempt == at:
            return None
        if self.active and state is INTERLOCK_SUSPEND[0]:
            self.attempt = at
            key, (reason, stop_id) = next(iter(self.active.items()))
            return INTERLOCK_SUSPEND[1], reason, stop_id, key
        if not self.active and self.suspended and state is INTERLOCK_RESUME[0]:
            self.attempt = at
            return INTERLOCK_RESUME[1], "interlock cleared", 0, self.released
        return None

    def entered(self, state: State, skipped: tuple[State, ...], by_interlock: bool) -> None:
        """The unit entered ``state`` (through ``skipped``): the suspension is the interlocks'
        when they caused Suspending, and no longer once the unit left the Suspend states."""
        if by_interlock and (state is State.SUSPENDING or State.SUSPENDING in skipped):
            self.suspended = True
        elif state is not State.SUSPENDING and state is not State.SUSPENDED:
            self.suspended = False
        self.busy = bool(self.active) or self.suspended
