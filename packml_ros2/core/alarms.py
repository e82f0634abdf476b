"""Alarms and warnings (docs/packml.md §7).

An alarm is keyed by (ID, Value). It latches: once raised it stays listed, with ``trigger`` showing
whether the condition is active now, until an alarm reset finds it inactive. Re-activation before
the reset is the same event. Operators acknowledge once. The first alarm per unit, per EM and per
category is kept as first-out until it is cleared explicitly or the unit enters Starting. The
category decides the reaction (Abort / Stop / Hold / Suspend / none), overridable per alarm;
warnings never act.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any, TypeVar

from .numbers import Cmd
from .rules import DEFAULT_REACTIONS, NUM_CATEGORIES, REACTIONS, Alert, Watch


class Kind(IntEnum):
    """Mirrors ``packml_interfaces/msg/Alarm`` KIND_*."""

    ALARM = 0
    WARNING = 1
    COMMAND = 2
    EVENT = 3


class OperatorState(IntEnum):
    ACTIVE_UNACKNOWLEDGED = 0
    INACTIVE_UNACKNOWLEDGED = 1
    ACKNOWLEDGED = 2


@dataclass(frozen=True, slots=True)
class AlarmDef:
    """An alarm or warning from the configuration."""

    id: int
    value: int
    message: str
    category: int
    warning: bool = False
    reaction: int | None = None  # None = by category
    em: str = ""


@dataclass(slots=True, eq=False)
class AlarmEvent:
    """One alarm/warning occurrence (or a command stop reason / history event)."""

    id: int
    value: int
    message: str
    category: int
    kind: Kind
    time: float  # first occurrence (node clock, seconds)
    em: str = ""
    source: str = ""
    reaction: int = 0
    trigger: bool = True
    latched: bool = True
    ack_time: float | None = None
    cleared_time: float | None = None
    activations: int = 1
    serial: int = 0  #: the unit's number of the occurrence (persistence journals changes by it)

    @property
    def key(self) -> tuple[int, int]:
        return (self.id, self.value)

    @property
    def acknowledged(self) -> bool:
        return self.ack_time is not None

    @property
    def operator_state(self) -> OperatorState:
        if self.ack_time is not None:
            return OperatorState.ACKNOWLEDGED
        if self.trigger:
            return OperatorState.ACTIVE_UNACKNOWLEDGED
        return OperatorState.INACTIVE_UNACKNOWLEDGED

    def label(self) -> str:
        """``'65/0 "Stop PB pressed" (category 2)'``"""
        return f'{self.id}/{self.value} "{self.message}" (category {self.category})'

    def to_dict(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "value": self.value,
            "message": self.message,
            "category": self.category,
            "kind": int(self.kind),
            "time": self.time,
            "em": self.em,
            "source": self.source,
            "reaction": self.reaction,
            "trigger": self.trigger,
            "latched": self.latched,
            "ack_time": self.ack_time,
            "cleared_time": self.cleared_time,
            "activations": self.activations,
            "serial": self.serial,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> AlarmEvent:
        """From :meth:`to_dict` (fields it does not know are left out: older or newer stores)."""
        known = {k: v for k, v in d.items() if k in _EVENT_FIELDS}
        known["kind"] = Kind(known["kind"])
        return cls(**known)


_EVENT_FIELDS = frozenset(AlarmEvent.__dataclass_fields__)
#: (The reactions are the rule book's, core/rules.py section 5b; named here for config.py.)
__all__ = [
    "DEFAULT_REACTIONS",
    "NUM_CATEGORIES",
    "REACTIONS",
    "AlarmDef",
    "AlarmEvent",
    "AlarmManager",
    "Kind",
    "OperatorState",
    "Raised",
]


@dataclass(frozen=True, slots=True)
class Raised:
    """What raising an alarm did: the event, and the reaction to apply now (0 = none)."""

    event: AlarmEvent
    new: bool
    rising: bool
    reaction: int


#: The orders of a query of alarms, by the key of an entry's (category, time): declared once for
#: the unit's query_alarms, the PLC bridge's and ``packml alarms`` on the latched list.
ORDERS: dict[str, Callable[[int, float], tuple[float, ...]]] = {
    "time": lambda category, time: (time,),
    "category": lambda category, time: (category, time),
    "newest": lambda category, time: (-time,),
}

T = TypeVar("T")


def select(
    items: Iterable[T],
    active_only: bool,
    category: int | None,
    sort: str,
    view: Callable[[T], tuple[bool, int, float]],
) -> list[T]:
    """``items`` filtered (only those whose condition is active, only ``category``) and ordered
    by ``sort`` (:data:`ORDERS`); ``view(item)`` = (trigger, category, time)."""
    if sort not in ORDERS:
        raise ValueError(f"sort must be one of {', '.join(ORDERS)}, not {sort!r}")
    order = ORDERS[sort]
    views = [(view(item), item) for item in items]
    kept = [
        (order(cat, time), item)
        for (trigger, cat, time), item in views
        if (trigger or not active_only) and (category is None or cat == category)
    ]
    return [item for _, item in sorted(kept, key=lambda pair: pair[0])]


def select_events(
    events: Iterable[AlarmEvent],
    active_only: bool = False,
    category: int | None = None,
    sort: str = "time",
) -> list[AlarmEvent]:
    """:func:`select` for the engine's own events."""
    return select(
        events, active_only, category, sort, lambda ev: (ev.trigger, ev.category, ev.time)
    )


@dataclass
class AlarmManager:
    """Active/latched alarms and warnings, first-outs, the history ring and the query."""

    defs: Mapping[tuple[int, int], AlarmDef]
    reactions: Mapping[int, int] = field(default_factory=lambda: dict(DEFAULT_REACTIONS))
    alarm_capacity: int = 64
    warning_capacity: int = 64
    history_capacity: int = 256
    #: The unit's alert: its ``ALARM`` bit is set while an active alarm has a reaction.
    alert: Alert = field(default_factory=Alert)

    def __post_init__(self) -> None:
        self.current: dict[tuple[int, int], AlarmEvent] = {}  # alarms and warnings, oldest first
        self.history: deque[AlarmEvent] = deque(maxlen=self.history_capacity)  # newest first
        self.history_dropped = 0
        self.first_out: AlarmEvent | None = None
        self.first_out_by_category: dict[int, AlarmEvent] = {}
        self.first_out_by_em: dict[str, AlarmEvent] = {}
        self.version = 0  # +1 on every change (publishers compare)
        self.blocking_version = 0  # +1 when the set of active reacting alarms changes
        self.serial = 0  # the last occurrence's number
        #: Occurrences changed since taken (take_changed), by serial; None: not tracked (a unit
        #: without persistence).
        self.changed: dict[int, AlarmEvent] | None = None

    # -- raising and clearing ----------------------------------------------------------------------
    def full(self) -> bool:
        """Whether the list holds as many alarms and warnings as it takes unconfigured ones in:
        twice what Admin.Alarm[] and Warning[] show (beyond that, only configured alarms are
        raised: a flood of made-up ones must not grow memory)."""
        return len(self.current) >= 2 * (self.alarm_capacity + self.warning_capacity)

    def definition(self, alarm_id: int, value: int) -> AlarmDef | None:
        return self.defs.get((alarm_id, value))

    def reaction_of(self, d: AlarmDef) -> int:
        if d.warning:
            return 0
        if d.reaction is not None:
            return d.reaction
        return self.reactions.get(d.category, 0)

    def raise_(self, d: AlarmDef, now: float, source: str = "", em: str = "") -> Raised:
        """Set the condition of ``d`` active."""
        ev = self.current.get((d.id, d.value))
        reaction = self.reaction_of(d)
        if ev is not None:
            if ev.trigger:
                return Raised(ev, new=False, rising=False, reaction=0)
            ev.trigger = True
            ev.cleared_time = None
            ev.activations += 1
            self._touch(ev)
            self._changed(reaction)
            return Raised(ev, new=False, rising=True, reaction=reaction)
        ev = AlarmEvent(
            id=d.id,
            value=d.value,
            message=d.message,
            category=d.category,
            kind=Kind.WARNING if d.warning else Kind.ALARM,
            time=now,
            em=em or d.em,
            source=source,
            reaction=reaction,
        )
        self.current[ev.key] = ev
        self._push_history(ev)
        if not d.warning:
            if self.first_out is None:
                self.first_out = ev
            self.first_out_by_category.setdefault(ev.category, ev)
            if ev.em:
                self.first_out_by_em.setdefault(ev.em, ev)
        self._changed(reaction)
        return Raised(ev, new=True, rising=True, reaction=reaction)

    def clear(self, alarm_id: int, value: int, now: float) -> AlarmEvent | None:
        """The condition went inactive; the alarm stays latched. None if it was not active."""
        ev = self.current.get((alarm_id, value))
        if ev is None or not ev.trigger:
            return None
        ev.trigger = False
        ev.cleared_time = now
        self._touch(ev)
        self._changed(ev.reaction)
        return ev

    def log_event(self, message: str, now: float, source: str = "unit", event_id: int = 0) -> None:
        """A history entry that is not an alarm ("unit restarted", "EM gripper switched inactive")."""
        ev = AlarmEvent(
            event_id, 0, message, 9, Kind.EVENT, now, source=source, trigger=False, latched=False
        )
        self._push_history(ev)
        self.version += 1

    def _push_history(self, ev: AlarmEvent) -> None:
        self.serial += 1
        ev.serial = self.serial
        if len(self.history) == self.history.maxlen:
            self.history_dropped += 1
        self.history.appendleft(ev)
        self._touch(ev)

    def _touch(self, ev: AlarmEvent) -> None:
        if self.changed is not None:
            self.changed[ev.serial] = ev

    def take_changed(self) -> list[AlarmEvent]:
        """The occurrences changed since the last call, oldest first (starts the tracking)."""
        if self.changed is None:
            self.changed = {}
            return []
        out = sorted(self.changed.values(), key=lambda ev: ev.serial)
        self.changed.clear()
        return out

    def _changed(self, reaction: int) -> None:
        self.version += 1
        if reaction:
            self.blocking_version += 1
            self.alert.set(
                Watch.ALARM, any(ev.trigger and ev.reaction for ev in self.current.values())
            )

    # -- operator actions --------------------------------------------------------------------------
    def acknowledge(self, key: tuple[int, int] | None, now: float) -> int:
        """Acknowledge one alarm (``key``) or all; returns how many were acknowledged now."""
        targets = self.current.values() if key is None else [self.current[key]]
        n = 0
        for ev in targets:
            if ev.ack_time is None:
                ev.ack_time = now
                self._touch(ev)
                n += 1
        if n:
            self.version += 1
        return n

    def reset(self) -> int:
        """Drop latched alarms whose condition is no longer active; active ones stay."""
        gone = [k for k, ev in self.current.items() if not ev.trigger]
        for k in gone:
            self.current[k].latched = False
            self._touch(self.current[k])
            del self.current[k]
        if gone:
            self.version += 1
        return len(gone)

    def clear_first_out(self) -> bool:
        had = self.first_out is not None or bool(self.first_out_by_category)
        self.first_out = None
        self.first_out_by_category.clear()
        self.first_out_by_em.clear()
        if had:
            self.version += 1
        return had

    # -- reading -----------------------------------------------------------------------------------
    def alarms(self) -> list[AlarmEvent]:
        return [ev for ev in self.current.values() if ev.kind is Kind.ALARM]

    def warnings(self) -> list[AlarmEvent]:
        return [ev for ev in self.current.values() if ev.kind is Kind.WARNING]

    def listed(self, warnings: bool = False) -> tuple[list[AlarmEvent], int]:
        """``Admin.Alarm[]`` (or ``Warning[]``) up to its capacity, and the overflow count: a full
        list never overwrites, it counts what did not fit."""
        items = self.warnings() if warnings else self.alarms()
        cap = self.warning_capacity if warnings else self.alarm_capacity
        return items[:cap], max(0, len(items) - cap)

    def active_count(self) -> int:
        return sum(1 for ev in self.current.values() if ev.trigger and ev.kind is Kind.ALARM)

    def unacknowledged_count(self) -> int:
        return sum(
            1 for ev in self.current.values() if ev.ack_time is None and ev.kind is Kind.ALARM
        )

    def blocking(self, blocked_by: Mapping[int, frozenset[Cmd]], cmd: int) -> AlarmEvent | None:
        """The first active alarm whose reaction refuses ``cmd`` (``blocked_by``: reaction ->
        the commands it refuses, :data:`.rules.BLOCKED_BY_REACTION`)."""
        for ev in self.current.values():
            if ev.trigger and ev.reaction and cmd in blocked_by.get(ev.reaction, ()):
                return ev
        return None

    def banner(self) -> str:
        """One line for operator screens: the unit's first-out if still active, else the oldest
        active alarm, with how many more are active."""
        active = [ev for ev in self.alarms() if ev.trigger]
        if not active:
            return ""
        first = self.first_out if self.first_out in active else active[0]
        where = f" [{first.em}]" if first.em else ""
        more = f" (+{len(active) - 1} more)" if len(active) > 1 else ""
        return f"ALARM {first.id}/{first.value} cat {first.category}: {first.message}{where}{more}"

    def query(
        self,
        active_only: bool = False,
        category: int | None = None,
        sort: str = "time",
        include_warnings: bool = False,
        history: bool = False,
    ) -> list[AlarmEvent]:
        """Filter (active only, category) and sort (``time``, ``category``+time, ``newest``)."""
        source: Iterable[AlarmEvent] = self.history if history else self.current.values()
        kinds = {Kind.ALARM, Kind.WARNING} if include_warnings else {Kind.ALARM}
        if history:
            kinds |= {Kind.EVENT, Kind.COMMAND}
        return select_events([ev for ev in source if ev.kind in kinds], active_only, category, sort)

    # -- persistence -------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """For persistence (saved at every transition): rebuilt only when something changed."""
        cached = self.__dict__.get("_saved")
        if cached is None or cached[0] != self.version:
            document = {
                "history": [ev.to_dict() for ev in self.history],
                "history_dropped": self.history_dropped,
            }
            self._saved = cached = (self.version, document)
        return cached[1]

    def restore(self, data: dict[str, Any]) -> None:
        self.history.clear()
        self.history.extend(AlarmEvent.from_dict(d) for d in data.get("history", []))
        self.history_dropped = int(data.get("history_dropped", 0))
        # occurrences saved before they had numbers are numbered after the others, oldest first
        self.serial = max((ev.serial for ev in self.history), default=0)
        for n, ev in enumerate(reversed([ev for ev in self.history if not ev.serial]), 1):
            ev.serial = self.serial + n
        self.serial = max((ev.serial for ev in self.history), default=0)
        self.version += 1
