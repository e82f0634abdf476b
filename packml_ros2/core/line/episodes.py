"""Stop episodes of a line and their root cause (first-out).

When the line stops producing (one of its units leaves Execute while all were in it), an
**episode** opens; it ends when every unit is back in Execute. Each unit that left Execute during
the episode is a :class:`Departure` with *how* it left:

- ``internal``: its own reason — an alarm, a command at the unit (operator, HMI, OPC UA, an EM's
  request), a timeout, a lost EM, the end of a run, a mode change, the unit itself lost;
- ``blocked`` / ``starved``: its own equipment reports it cannot discharge / is not fed;
- ``propagated``: the coordinator suspended it because a neighbour is blocked or starved (the
  interlock rules), or commanded it in reaction to a lost unit;
- ``cell``: a cell command (the coordinator's sequence, asked by someone at the cell).

The **root cause** is the earliest departure that nothing explains: a blocked unit is explained
by a unit *downstream* of it that left Execute at or before it, a starved one by a unit
*upstream*; propagated and cell departures are explained by what caused them. When every
departure is explained, the root is the cause the first one names (the blocked neighbour, the
lost unit) or the cell itself (unit ``""``) for a cell command.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

from .losses import BLOCKED, STARVED, UNPLANNED

INTERNAL, OWN_BLOCKED, OWN_STARVED, PROPAGATED, CELL, PENDING = (
    "internal", "blocked", "starved", "propagated", "cell", "pending",
)  # fmt: skip
KINDS = (INTERNAL, OWN_BLOCKED, OWN_STARVED, PROPAGATED, CELL, PENDING)


@dataclass
class Departure:
    """A unit left Execute (or its state became unknown) at ``time`` (ns)."""

    unit: str
    time: int
    sequence: int
    to_state: int
    kind: str = PENDING  #: one of :data:`KINDS`; pending until its transition arrived
    label: str = ""  #: why, one line: "alarm 202: Infeed jam", "loader blocked", ...
    trigger: int = -1
    command: int = 0
    source: str = ""
    detail: str = ""
    cause_unit: str = ""  #: propagated: the neighbour it was propagated from
    condition: str = ""  #: propagated: blocked | starved ('' for a lost unit's reaction)
    bucket: str = UNPLANNED  #: the loss bucket of the unit's stop
    reason_id: int = 0  #: the unit's StopReason ID at the departure (0: not known yet)

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Departure:
        return cls(**{k: d[k] for k in cls.__dataclass_fields__ if k in d})


@dataclass(frozen=True)
class Root:
    unit: str  #: '' = the cell (a cell command)
    bucket: str
    reason: str
    departure: Departure | None


@dataclass
class Episode:
    id: int
    start: int
    end: int | None = None
    departures: list[Departure] = field(default_factory=list)
    #: the root unit's StopReason as its admin data told it (id, value, message, category,
    #: source, em), once it arrived
    stop_reason: dict[str, Any] | None = None

    @property
    def open(self) -> bool:
        return self.end is None

    def duration(self, now: int) -> int:
        return (self.end if self.end is not None else now) - self.start

    def root(self, order: Sequence[str]) -> Root:
        return root_cause(self.departures, order)

    def to_dict(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "start": self.start,
            "end": self.end,
            "departures": [d.to_dict() for d in self.departures],
            "stop_reason": self.stop_reason,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Episode:
        return cls(
            int(d["id"]),
            int(d["start"]),
            None if d.get("end") is None else int(d["end"]),
            [Departure.from_dict(x) for x in d.get("departures", [])],
            d.get("stop_reason"),
        )

    def copy(self) -> Episode:
        return Episode(
            self.id,
            self.start,
            self.end,
            [replace(d) for d in self.departures],
            dict(self.stop_reason) if self.stop_reason else None,
        )


def explained(d: Departure, before: Sequence[Departure], position: Mapping[str, int]) -> bool:
    """Whether ``d`` is explained by propagation or by a neighbour that left earlier."""
    if d.kind in (PROPAGATED, CELL):
        return True
    if d.kind not in (OWN_BLOCKED, OWN_STARVED):
        return False
    here = position.get(d.unit, 0)
    for e in before:
        there = position.get(e.unit, 0)
        if d.kind == OWN_BLOCKED and there > here:
            return True
        if d.kind == OWN_STARVED and there < here:
            return True
    return False


def root_cause(departures: Sequence[Departure], order: Sequence[str]) -> Root:
    """The first-out of ``departures`` (see the module docstring)."""
    position = {u: i for i, u in enumerate(order)}
    ranked = sorted(departures, key=lambda d: (d.time, position.get(d.unit, 0)))
    for i, d in enumerate(ranked):
        earlier = [e for e in ranked[:i] if e.time <= d.time]
        if not explained(d, earlier, position):
            return Root(d.unit, d.bucket, d.label, d)
    if not ranked:
        return Root("", UNPLANNED, "", None)
    first = ranked[0]
    if first.kind == PROPAGATED and first.cause_unit:
        bucket = {"blocked": BLOCKED, "starved": STARVED}.get(first.condition, UNPLANNED)
        return Root(first.cause_unit, bucket, first.label, first)
    if first.kind == CELL:
        return Root("", first.bucket, first.label, first)
    return Root(first.unit, first.bucket, first.label, first)
