"""The ``line:`` block of a cell file: the units' order on the line, its output, the shift
calendar, the store of its episodes and losses (``config/reference_cell.yaml`` documents it)."""

from __future__ import annotations

import itertools
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol
from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

from .. import schema as sc
from ..schema import Node, invalid
from .calendar import DAY_S, DAYS, Break, Calendar, Shift

#: The line's store beside the units' (the first unit's directory); a dot: no unit has this name.
LINE_STORE = "coordinator.line.sqlite3"
_TIME = re.compile(r"^([01]?\d|2[0-3]):([0-5]\d)(?::([0-5]\d))?$")
MAX_SHIFTS = 16
MAX_BREAKS = 16
#: the keys of the ``line:`` block
KEYS = (
    "order",
    "output_unit",
    "shifts",
    "timezone",
    "store",
    "publish_period",
    "changeover_modes",
)
#: the modes whose time is a changeover unless the line names others (lower case)
CHANGEOVER_MODES = ("changeover",)


class InterlockLike(Protocol):
    """An interlock rule (core.config.InterlockRule)."""

    @property
    def unit(self) -> str: ...
    @property
    def condition(self) -> str: ...
    @property
    def suspend(self) -> tuple[str, ...]: ...


@dataclass(frozen=True)
class LineConfig:
    #: units from upstream to downstream
    order: tuple[str, ...] = ()
    #: the unit whose counts are the line's output (processed, defective, MachDesignSpeed)
    output_unit: str = ""
    shifts: tuple[Shift, ...] = ()
    timezone: str = "UTC"
    #: SQLite file of episodes and losses (None: in memory only)
    store: str | None = None
    #: seconds between loss summaries published on ``line/losses``
    publish_period: float = 5.0
    #: names of the modes (lower case) whose time is the ``changeover`` bucket, not planned_stop
    changeover_modes: tuple[str, ...] = CHANGEOVER_MODES
    calendar: Calendar = field(default_factory=Calendar, compare=False)


def time_of_day(n: Node) -> int:
    """``"HH:MM"`` or ``"HH:MM:SS"`` -> seconds after midnight (``"24:00"`` is midnight too)."""
    v = n.value
    if isinstance(v, int) and not isinstance(v, bool):
        raise invalid("quote times of day ('06:00'): YAML reads 22:30 unquoted as a number")
    if not isinstance(v, str):
        raise invalid(f"{sc.shown(v)} is not a time of day ('HH:MM')")
    if v.strip() == "24:00":
        return 0
    m = _TIME.match(v.strip())
    if m is None:
        raise invalid(f"{sc.shown(v)} is not a time of day ('HH:MM' or 'HH:MM:SS')")
    return int(m[1]) * 3600 + int(m[2]) * 60 + int(m[3] or 0)


def _days(n: Node) -> frozenset[int]:
    out = set()
    for e in n.elements():
        word = str(e.value).strip().lower()[:3]
        if word not in DAYS:
            e.error(f"{sc.shown(e.value)} is not a weekday ({', '.join(DAYS)})")
            continue
        out.add(DAYS.index(word))
    if not out:
        raise invalid("a shift needs at least one day")
    return frozenset(out)


def _shift(name: str, n: Node) -> Shift | None:
    before = len(n.problems)
    n.check_keys({"start", "end", "days", "breaks"})
    for key in ("start", "end"):
        if key not in n.mapping():
            n.error(f"a shift needs {key} ('HH:MM')")
    start = n.get("start", time_of_day, 0)
    end = n.get("end", time_of_day, 0)
    length = (end - start) % DAY_S or DAY_S
    breaks = []
    nodes = n.list_at("breaks")
    if len(nodes) > MAX_BREAKS:
        n.child("breaks", None).error(f"{len(nodes)} breaks, at most {MAX_BREAKS}")
    for e in nodes[:MAX_BREAKS]:
        e.check_keys({"name", "start", "end"})
        b = Break(
            e.get("name", sc.text, "break") or "break",
            e.get("start", time_of_day, 0),
            e.get("end", time_of_day, 0),
        )
        offset = (b.start - start) % DAY_S
        b_length = (b.end - b.start) % DAY_S
        if not b_length or offset + b_length > length:
            e.error(f"break {b.name!r} must lie inside the shift ({_hhmm(start)}-{_hhmm(end)})")
            continue
        breaks.append(b)
    days = n.get("days", _days, frozenset(range(7)))
    if len(n.problems) > before:
        return None
    return Shift(name, start, end, days, tuple(breaks))


def _hhmm(seconds: int) -> str:
    return f"{seconds // 3600:02d}:{seconds // 60 % 60:02d}"


def _overlaps(shifts: Sequence[Shift]) -> str | None:
    """Two shifts of the same week that overlap, named, or None."""
    spans: list[tuple[int, int, str]] = []
    for s in shifts:
        for day in s.days:
            a = day * DAY_S + s.start
            spans.append((a, a + s.length, s.name))
            spans.append((a + 7 * DAY_S, a + 7 * DAY_S + s.length, s.name))
    spans.sort()
    for (_a1, b1, n1), (a2, _, n2) in itertools.pairwise(spans):
        if a2 < b1:
            return f"shifts {n1!r} and {n2!r} overlap"
    return None


def _mode_name(n: Node) -> str:
    word = sc.text(n).strip().lower()
    if not word:
        raise invalid("a mode name cannot be empty")
    return word


def _mode_names(n: Node) -> tuple[str, ...]:
    """Mode names (case-insensitive: lower case), each once; [] for none."""
    out = (e.parse(_mode_name, "") for e in n.elements())
    return tuple(dict.fromkeys(m for m in out if m))


def default_order(units: Sequence[str], rules: Sequence[InterlockLike]) -> tuple[str, ...]:
    """Upstream to downstream from the interlock rules (a unit ``blocked`` suspends the units
    upstream of it, ``starved`` those downstream), stable in configuration order otherwise."""
    after: dict[str, set[str]] = {u: set() for u in units}  # unit -> units downstream of it
    for r in rules:
        for other in r.suspend:
            if other not in after or r.unit not in after or other == r.unit:
                continue
            if r.condition == "blocked":
                after[other].add(r.unit)
            else:
                after[r.unit].add(other)
    order: list[str] = []
    placed: set[str] = set()
    while len(order) < len(units):
        ready = [
            u
            for u in units
            if u not in placed and not any(u in after[p] for p in units if p not in placed)
        ]
        nxt = ready[0] if ready else next(u for u in units if u not in placed)  # a cycle
        order.append(nxt)
        placed.add(nxt)
    return tuple(order)


def parse_line(
    n: Node,
    cell: str,
    units: Sequence[str],
    rules: Sequence[InterlockLike],
    base_dir: Path,
    default_store: str | None,
) -> LineConfig:
    """Validate the ``line:`` block (``n.value`` may be None: the defaults). ``default_store``:
    the store's path when the block names none (beside the units' stores; None: no unit has one,
    the line keeps its losses in memory)."""
    if n.value is None:
        n = Node({}, n.path, n.problems)
    n.check_keys(set(KEYS))
    names = {u: u for u in units}

    def order(x: Node) -> tuple[str, ...]:
        out = tuple(e.parse(sc.choice(names), "") for e in x.elements())
        if len(set(out)) != len(out):
            x.error("a unit is listed twice")
        missing = [u for u in units if u not in out]
        if missing:
            x.error(f"every unit is on the line: {', '.join(missing)} missing")
        return out

    none: tuple[str, ...] = ()
    line_order = n.get("order", order, none) or default_order(units, rules)
    output = n.get("output_unit", sc.choice(names), line_order[-1] if line_order else "")

    def zone(x: Node) -> str:
        text = sc.text(x)
        try:
            ZoneInfo(text)
        except (ZoneInfoNotFoundError, ValueError):
            raise invalid(
                f"{sc.shown(text)} is not a time zone (an IANA name: UTC, Europe/Berlin)"
            ) from None
        return text

    timezone = n.get("timezone", zone, "UTC")
    shifts: list[Shift] = []
    items = n.items_at("shifts")
    if len(items) > MAX_SHIFTS:
        n.child("shifts", None).error(f"{len(items)} shifts, at most {MAX_SHIFTS}")
    for key, child in items[:MAX_SHIFTS]:
        Node(key, child.path, child.problems).parse(sc.name, "")
        shift = _shift(key, child)
        if shift is not None:
            shifts.append(shift)
    clash = _overlaps(shifts)
    if clash:
        n.child("shifts", None).error(clash)
    store: str | None = default_store
    raw: Mapping[str, Any] = n.mapping()
    if "store" in raw and raw["store"] in (None, False):
        store = None
    elif "store" in raw:
        store = n.get("store", sc.text, "") or None
    if store:
        p = Path(os.path.expanduser(store.replace("{cell}", cell or "cell")))
        store = str(p if p.is_absolute() else base_dir / p)
    return LineConfig(
        order=line_order,
        output_unit=output,
        shifts=tuple(shifts),
        timezone=timezone,
        store=store,
        publish_period=n.get("publish_period", sc.number(0.1, 3600.0), 5.0),
        changeover_modes=n.get("changeover_modes", _mode_names, CHANGEOVER_MODES),
        calendar=Calendar(tuple(shifts), timezone),
    )
