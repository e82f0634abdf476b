"""The shift calendar of a line (``line.shifts`` of the cell file): which shift a moment belongs
to, and which moments are planned downtime (a break, or no shift at all).

Times are integer nanoseconds since the epoch (the line's clock); shift times are times of day in
the calendar's ``timezone`` (an IANA name, default UTC: the same file gives the same shifts on
every machine, so a replay in CI agrees with the plant). A shift whose end is not after its start
runs past midnight (``22:00``-``06:00``); ``days`` are the weekdays its instances *start* on.
Breaks are times of day inside the shift. Daylight-saving changes are followed (a night shift
across one is an hour longer or shorter).

The calendar spans the dates a time of the line can name: :data:`FIRST_DAY` to :data:`LAST_DAY`
(a ROS time is int64 nanoseconds: 1970 to 2262). A date or a time outside it names no shift (a
query of ``shift:9999-12-31 early`` is "no shift", not an overflow of the date arithmetic).
"""

from __future__ import annotations

import datetime as _dt
from collections.abc import Iterator
from dataclasses import dataclass
from functools import lru_cache
from zoneinfo import ZoneInfo

NS = 1_000_000_000
DAY_S = 86_400
DAYS = ("mon", "tue", "wed", "thu", "fri", "sat", "sun")
NO_SHIFT = "no shift"
#: The days the calendar knows (inclusive): what a ROS time (int64 ns since the epoch) can name,
#: less a margin for the time zone and the days :meth:`Calendar.instances` looks back.
FIRST_DAY = _dt.date(1970, 1, 3)
LAST_DAY = _dt.date(2262, 4, 1)
#: ns: the times the calendar knows, midnight UTC of FIRST_DAY to midnight UTC after LAST_DAY
FIRST_NS = (FIRST_DAY - _dt.date(1970, 1, 1)).days * DAY_S * NS
LAST_NS = (LAST_DAY - _dt.date(1970, 1, 1) + _dt.timedelta(days=1)).days * DAY_S * NS


@dataclass(frozen=True)
class Break:
    name: str
    start: int  #: seconds after midnight
    end: int


@dataclass(frozen=True)
class Shift:
    name: str
    start: int  #: seconds after midnight
    end: int  #: not after start: the next day
    days: frozenset[int] = frozenset(range(7))  #: weekdays (0 = Monday) instances start on
    breaks: tuple[Break, ...] = ()

    @property
    def length(self) -> int:
        """Seconds (on a day without a clock change)."""
        return (self.end - self.start) % DAY_S or DAY_S


@dataclass(frozen=True)
class Instance:
    """One shift on one day: ``key`` names it (``2025-03-04 early``)."""

    key: str
    shift: str
    start: int  #: ns
    end: int  #: ns
    breaks: tuple[tuple[str, int, int], ...]  #: (name, start ns, end ns)


@dataclass(frozen=True)
class Piece:
    """A part of an interval that lies in one shift instance (or in none) and is either planned
    (a break, or no shift) or not: ``planned`` names why ('' = not planned)."""

    start: int
    end: int
    shift: str  #: instance key, '' = no shift
    planned: str


class Calendar:
    """``Calendar(shifts, timezone)``; without shifts every moment is production time and
    belongs to no shift."""

    def __init__(self, shifts: tuple[Shift, ...] = (), timezone: str = "UTC") -> None:
        self.shifts = shifts
        self.timezone = timezone
        self.zone = ZoneInfo(timezone)

    def __bool__(self) -> bool:
        return bool(self.shifts)

    def _at(self, day: _dt.date, seconds: int) -> int:
        """ns of ``seconds`` after midnight of ``day`` (seconds may exceed a day)."""
        extra, seconds = divmod(seconds, DAY_S)
        d = day + _dt.timedelta(days=extra)
        local = _dt.datetime(
            d.year,
            d.month,
            d.day,
            seconds // 3600,
            seconds // 60 % 60,
            seconds % 60,
            tzinfo=self.zone,
        )
        return int(local.timestamp()) * NS

    @lru_cache(maxsize=64)  # noqa: B019 (the calendar lives as long as its line)
    def _day(self, day: _dt.date) -> tuple[Instance, ...]:
        """The instances starting on ``day``."""
        out = []
        for shift in self.shifts:
            if day.weekday() not in shift.days:
                continue
            end_s = shift.end if shift.end > shift.start else shift.end + DAY_S
            breaks = []
            for b in shift.breaks:  # (validated to lie inside the shift)
                offset = (b.start - shift.start) % DAY_S
                length = (b.end - b.start) % DAY_S
                breaks.append(
                    (
                        b.name,
                        self._at(day, shift.start + offset),
                        self._at(day, shift.start + offset + length),
                    )
                )
            out.append(
                Instance(
                    f"{day.isoformat()} {shift.name}",
                    shift.name,
                    self._at(day, shift.start),
                    self._at(day, end_s),
                    tuple(breaks),
                )
            )
        return tuple(sorted(out, key=lambda i: i.start))

    def instances(self, a: int, b: int) -> Iterator[Instance]:
        """Shift instances overlapping [a, b), by start (those of days the calendar knows)."""
        a, b = max(a, FIRST_NS), min(b, LAST_NS)
        if not self.shifts or b <= a:
            return
        first = _dt.datetime.fromtimestamp(a // NS, self.zone).date() - _dt.timedelta(days=2)
        last = _dt.datetime.fromtimestamp(b // NS, self.zone).date()
        day = first
        while day <= last:
            for inst in self._day(day):
                if inst.start < b and inst.end > a:
                    yield inst
            day += _dt.timedelta(days=1)

    def instance_at(self, t: int) -> Instance | None:
        return next(self.instances(t, t + 1), None)

    def instance(self, key: str) -> Instance | None:
        """The instance named ``key`` (``YYYY-MM-DD name``)."""
        day_text, _, name = key.partition(" ")
        try:
            day = _dt.date.fromisoformat(day_text)
        except ValueError:
            return None
        if not FIRST_DAY <= day <= LAST_DAY:
            return None
        return next((i for i in self._day(day) if i.shift == name), None)

    def previous(self, t: int, back: int = 1) -> Instance | None:
        """The instance ``back`` shifts before the one at ``t`` (or before ``t``)."""
        found: list[Instance] = []
        span = 8 * DAY_S * NS
        for inst in self.instances(t - span * max(1, back), t + 1):
            if inst.start <= t:
                found.append(inst)
        current = self.instance_at(t)
        if current is not None and found and found[-1] == current:
            found.pop()
        return found[-back] if len(found) >= back else None

    def pieces(self, a: int, b: int) -> list[Piece]:
        """[a, b) cut where a shift or a break begins or ends."""
        if b <= a:
            return []
        if not self.shifts:
            return [Piece(a, b, "", "")]
        out: list[Piece] = []
        t = a
        for inst in self.instances(a, b):
            if inst.start > t:
                out.append(Piece(t, min(inst.start, b), "", NO_SHIFT))
                t = min(inst.start, b)
            lo, hi = max(t, inst.start), min(b, inst.end)
            if hi <= lo:
                continue
            cuts = sorted(
                (max(lo, s), min(hi, e), name) for name, s, e in inst.breaks if s < hi and e > lo
            )
            u = lo
            for s, e, name in cuts:
                if s > u:
                    out.append(Piece(u, s, inst.key, ""))
                if e > max(u, s):
                    out.append(Piece(max(u, s), e, inst.key, f"break: {name}"))
                u = max(u, e)
            if u < hi:
                out.append(Piece(u, hi, inst.key, ""))
            t = hi
        if t < b:
            out.append(Piece(t, b, "", NO_SHIFT))
        return out
