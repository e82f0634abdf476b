"""Facts of a line's losses and the windows over them.

A **fact** is a closed piece of time of one scope in one bucket (:class:`Segment`) or a count
(:class:`Count`); each lies in one shift instance (or in none), the calendar having cut it. The
:class:`Ledger` adds facts to running totals per window — lifetime, since reset, each shift — and
keeps the last hour of facts for the rolling windows (15 min, 1 h). Any other span is asked of a
:class:`History` (the SQLite store, or :class:`MemoryHistory`). Open (not yet closed) time is
passed to each question as facts that are not kept (``open_parts``).

Everything is in integer nanoseconds: the totals of a window add up exactly.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from .losses import Totals

NS = 1_000_000_000
ROLLING: Mapping[str, int] = {"15min": 15 * 60 * NS, "1h": 3600 * NS}
RECENT = max(ROLLING.values())
MAX_SHIFTS_KEPT = 400  # shift instances whose totals stay in memory (older: the history)


@dataclass(frozen=True, slots=True)
class Segment:
    scope: str
    start: int
    end: int
    bucket: str
    reason: str
    shift: str = ""

    def to_list(self) -> list[Any]:
        return ["s", self.scope, self.start, self.end, self.bucket, self.reason, self.shift]


@dataclass(frozen=True, slots=True)
class Count:
    scope: str
    t: int
    processed: int
    defective: int
    net: int  #: ns the count takes at design speed
    good: int  #: ns the good count takes at design speed
    shift: str = ""

    def to_list(self) -> list[Any]:
        return [
            "c",
            self.scope,
            self.t,
            self.processed,
            self.defective,
            self.net,
            self.good,
            self.shift,
        ]


Fact = Segment | Count


def fact_of(x: Sequence[Any]) -> Fact:
    if x[0] == "s":
        return Segment(str(x[1]), int(x[2]), int(x[3]), str(x[4]), str(x[5]), str(x[6]))
    return Count(str(x[1]), int(x[2]), int(x[3]), int(x[4]), int(x[5]), int(x[6]), str(x[7]))


def add_clipped(out: dict[str, Totals], fact: Fact, a: int | None, b: int | None) -> None:
    """Add the part of ``fact`` in [a, b) (None: unbounded) to ``out`` (scope -> totals)."""
    if isinstance(fact, Segment):
        lo = fact.start if a is None else max(a, fact.start)
        hi = fact.end if b is None else min(b, fact.end)
        if hi > lo:
            out.setdefault(fact.scope, Totals()).add_time(fact.bucket, fact.reason, hi - lo)
    elif (a is None or fact.t >= a) and (b is None or fact.t < b):
        out.setdefault(fact.scope, Totals()).add_count(
            fact.processed, fact.defective, fact.net, fact.good
        )


class History(Protocol):
    """Where facts are kept for spans the ledger does not total itself."""

    def totals(self, a: int | None, b: int | None) -> dict[str, Totals]: ...


class MemoryHistory:
    """Every fact in a list (tests, replay)."""

    def __init__(self) -> None:
        self.facts: list[Fact] = []

    def add(self, facts: Iterable[Fact]) -> None:
        self.facts.extend(facts)

    def totals(self, a: int | None, b: int | None) -> dict[str, Totals]:
        out: dict[str, Totals] = {}
        for f in self.facts:
            add_clipped(out, f, a, b)
        return out


class Ledger:
    """Running totals per window; see the module docstring."""

    def __init__(self, history: History | None = None) -> None:
        self.history = history
        self.lifetime: dict[str, Totals] = {}
        self.reset: dict[str, Totals] = {}
        self.reset_at: int | None = None  #: None: never reset (since reset = lifetime)
        self.shifts: dict[str, dict[str, Totals]] = {}
        self.recent: deque[Fact] = deque()
        self.latest = 0  #: the latest time a fact reached

    # -- adding ----------------------------------------------------------------------------------
    def add(self, facts: Iterable[Fact]) -> None:
        for f in facts:
            add_clipped(self.lifetime, f, None, None)
            add_clipped(self.reset, f, self.reset_at, None)
            if f.shift:
                add_clipped(self.shifts.setdefault(f.shift, {}), f, None, None)
            self.recent.append(f)
            self.latest = max(self.latest, f.end if isinstance(f, Segment) else f.t)
        while len(self.shifts) > MAX_SHIFTS_KEPT:
            del self.shifts[next(iter(self.shifts))]
        horizon = self.latest - RECENT
        while self.recent and _end(self.recent[0]) < horizon:
            self.recent.popleft()

    def reset_now(self, t: int) -> None:
        """Start the since-reset window at ``t``."""
        self.reset_at = t
        self.reset = {}
        for f in self.recent:
            add_clipped(self.reset, f, t, None)

    # -- windows -----------------------------------------------------------------------------------
    def rolling(self, span: int, now: int, open_parts: Sequence[Fact]) -> dict[str, Totals]:
        out: dict[str, Totals] = {}
        for f in (*self.recent, *open_parts):
            add_clipped(out, f, now - span, now + 1)
        return out

    def totals(self, which: str, now: int, open_parts: Sequence[Fact]) -> dict[str, Totals]:
        """``lifetime``, ``reset``, ``shift:<key>``, ``15min`` or ``1h`` at ``now``."""
        if which in ROLLING:
            return self.rolling(ROLLING[which], now, open_parts)
        if which == "lifetime":
            base, a = self.lifetime, None
        elif which == "reset":
            base, a = self.reset, self.reset_at
        elif which.startswith("shift:"):
            key = which[6:]
            base, a = self.shifts.get(key, {}), None
            open_parts = [f for f in open_parts if f.shift == key]
        else:
            raise KeyError(which)
        out = {scope: t.copy() for scope, t in base.items()}
        for f in open_parts:
            add_clipped(out, f, a, None)
        return out

    def span(self, a: int | None, b: int | None, open_parts: Sequence[Fact]) -> dict[str, Totals]:
        """Any span [a, b), from the history (and the open parts)."""
        if self.history is None:
            raise LookupError("no history of facts: only the running windows are known")
        out = self.history.totals(a, b)
        for f in open_parts:
            add_clipped(out, f, a, b)
        return out

    # -- what a replay starts from ----------------------------------------------------------------
    def base(self, keep_shifts: Iterable[str]) -> dict[str, Any]:
        """The totals a replay needs to continue this ledger exactly (the windows that are still
        open: lifetime, since reset, the shifts named, the last hour)."""
        keep = set(keep_shifts)
        return {
            "lifetime": {s: t.to_dict() for s, t in self.lifetime.items()},
            "reset": {s: t.to_dict() for s, t in self.reset.items()},
            "reset_at": self.reset_at,
            "shifts": {
                k: {s: t.to_dict() for s, t in v.items()}
                for k, v in self.shifts.items()
                if k in keep
            },
            "recent": [f.to_list() for f in self.recent],
            "latest": self.latest,
        }

    def restore(self, base: Mapping[str, Any]) -> None:
        def scopes(d: Mapping[str, Any]) -> dict[str, Totals]:
            return {str(s): Totals.from_dict(t) for s, t in d.items()}

        self.lifetime = scopes(base.get("lifetime", {}))
        self.reset = scopes(base.get("reset", {}))
        reset_at = base.get("reset_at")
        self.reset_at = None if reset_at is None else int(reset_at)
        self.shifts = {str(k): scopes(v) for k, v in base.get("shifts", {}).items()}
        self.recent = deque(fact_of(x) for x in base.get("recent", []))
        self.latest = int(base.get("latest", 0))


def _end(f: Fact) -> int:
    return f.end if isinstance(f, Segment) else f.t
