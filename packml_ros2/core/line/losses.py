"""Loss buckets, their totals over a window and the OEE they give (integer nanoseconds, so the
buckets of a window add up to its elapsed time exactly).

Every nanosecond of a scope (a unit, or the line) falls into one bucket, with a reason:

- ``running``: in Execute (Production mode); split further by the counts into *productive*
  time (good count at MachDesignSpeed), *quality loss* (defective count at that speed) and
  *speed loss* (the rest of the running time);
- ``planned_stop``: a break or no shift (the shift calendar), another mode than Production, or
  stopped with a planned stop reason (``planned_stop_ids``, e.g. a cell Stop: 4006);
- ``changeover``: in a changeover mode (``line.changeover_modes``, default: a mode named
  ``changeover``), a product changeover; planned like ``planned_stop`` (a break or no shift in
  it stays ``planned_stop``);
- ``unplanned_stop``: stopped, aborted, completing ... with the stop reason (an alarm, a command
  and its source, a lost unit ...);
- ``blocked`` / ``starved``: suspended because the unit cannot discharge / is not fed;
- ``held``: Holding, Held, Unholding (internal conditions).

OEE = productive / (elapsed - planned stops - changeover) = Availability x Performance x Quality
with A = running / planned production time, P = (count at design speed) / running and
Q = good / processed.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

NS = 1_000_000_000
RUNNING, PLANNED, UNPLANNED, BLOCKED, STARVED, HELD = (
    "running", "planned_stop", "unplanned_stop", "blocked", "starved", "held",
)  # fmt: skip
CHANGEOVER = "changeover"
BUCKETS = (RUNNING, PLANNED, CHANGEOVER, UNPLANNED, BLOCKED, STARVED, HELD)
#: Planned time: not planned production time (not an availability loss).
PLANNED_BUCKETS = (PLANNED, CHANGEOVER)
#: Availability losses, in the waterfall's order.
DOWN = (UNPLANNED, BLOCKED, STARVED, HELD)
LINE = ""  #: the scope of the line itself (units are named)


@dataclass
class Totals:
    """What a window holds of one scope: ns per (bucket, reason), counts, and the count in ns at
    design speed (``net``: processed, ``good``: processed - defective)."""

    time: dict[tuple[str, str], int] = field(default_factory=dict)
    processed: int = 0
    defective: int = 0
    net: int = 0
    good: int = 0

    def add_time(self, bucket: str, reason: str, ns: int) -> None:
        if ns:
            key = (bucket, reason)
            self.time[key] = self.time.get(key, 0) + ns

    def add_count(self, processed: int, defective: int, net: int, good: int) -> None:
        self.processed += processed
        self.defective += defective
        self.net += net
        self.good += good

    def merge(self, other: Totals) -> None:
        for (bucket, reason), ns in other.time.items():
            self.add_time(bucket, reason, ns)
        self.add_count(other.processed, other.defective, other.net, other.good)

    def copy(self) -> Totals:
        out = Totals()
        out.merge(self)
        return out

    def to_dict(self) -> dict[str, Any]:
        return {
            "time": [[b, r, ns] for (b, r), ns in sorted(self.time.items())],
            "counts": [self.processed, self.defective, self.net, self.good],
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Totals:
        out = cls()
        for b, r, ns in d.get("time", []):
            out.add_time(str(b), str(r), int(ns))
        p, dfc, net, good = (int(x) for x in d.get("counts", [0, 0, 0, 0]))
        out.add_count(p, dfc, net, good)
        return out


def at_speed(count: int, design_speed: float) -> int:
    """ns a count takes at ``design_speed`` (per minute); 0 without a design speed."""
    return round(count * 60 * NS / design_speed) if design_speed > 0 else 0


@dataclass(frozen=True)
class Summary:
    """One scope over one window: the loss waterfall and OEE. ``performance`` is None without a
    design speed (then the running time counts as net: no speed loss is shown)."""

    scope: str
    elapsed: int
    buckets: tuple[tuple[str, str, int], ...]  #: (bucket, reason, ns), largest first per bucket
    planned: int
    changeover: int
    unplanned: int
    blocked: int
    starved: int
    held: int
    running: int
    speed_loss: int
    quality_loss: int
    productive: int
    processed: int
    defective: int
    availability: float
    performance: float | None
    quality: float
    oee: float

    @property
    def planned_production(self) -> int:
        return self.elapsed - self.planned - self.changeover

    def by_bucket(self, bucket: str) -> dict[str, int]:
        return {r: ns for b, r, ns in self.buckets if b == bucket}


def summarize(scope: str, totals: Totals, design_speed: float) -> Summary:
    """The waterfall of ``totals``; every part is an integer, and elapsed = planned + changeover
    + unplanned + blocked + starved + held + speed loss + quality loss + productive."""
    per: dict[str, int] = dict.fromkeys(BUCKETS, 0)
    for (bucket, _), ns in totals.time.items():
        per[bucket] = per.get(bucket, 0) + ns
    elapsed = sum(per.values())
    running = per[RUNNING]
    if design_speed > 0:
        net, good = totals.net, totals.good
        performance: float | None = net / running if running else 0.0
    else:  # no design speed: no speed loss can be told; quality still splits the running time
        net = running
        good = (
            running * (totals.processed - totals.defective) // totals.processed
            if totals.processed
            else running
        )
        performance = None
    speed_loss = running - net
    quality_loss = net - good
    planned_production = elapsed - sum(per[b] for b in PLANNED_BUCKETS)
    availability = running / planned_production if planned_production > 0 else 0.0
    quality = (totals.processed - totals.defective) / totals.processed if totals.processed else 0.0
    oee = good / planned_production if planned_production > 0 else 0.0
    ordered = sorted(
        ((b, r, ns) for (b, r), ns in totals.time.items() if ns),
        key=lambda x: (BUCKETS.index(x[0]), -x[2], x[1]),
    )
    return Summary(
        scope=scope,
        elapsed=elapsed,
        buckets=tuple(ordered),
        planned=per[PLANNED],
        changeover=per[CHANGEOVER],
        unplanned=per[UNPLANNED],
        blocked=per[BLOCKED],
        starved=per[STARVED],
        held=per[HELD],
        running=running,
        speed_loss=speed_loss,
        quality_loss=quality_loss,
        productive=good,
        processed=totals.processed,
        defective=totals.defective,
        availability=availability,
        performance=performance,
        quality=quality,
        oee=oee,
    )


# -- the LossScope message's view (packml_interfaces; read by attribute) -----------------------
#: the parts of a scope's time, in order (:func:`times_ns`)
TIMES = (
    "elapsed",
    PLANNED,
    CHANGEOVER,
    UNPLANNED,
    BLOCKED,
    STARVED,
    HELD,
    RUNNING,
    "speed_loss",
    "quality_loss",
    "productive",
)


def bucket_ns(buckets: Iterable[Any], bucket: str) -> int:
    """ns of ``bucket`` in ``buckets`` (LossBucket messages: ``bucket``, ``nanoseconds``)."""
    return sum(int(b.nanoseconds) for b in buckets if b.bucket == bucket)


def times_ns(s: Any) -> dict[str, int]:
    """The parts of a LossScope message in ns, in :data:`TIMES` order; they add up: elapsed =
    planned_stop + changeover + unplanned_stop + blocked + starved + held + running, running =
    speed_loss + quality_loss + productive. The message has no changeover field: its
    ``planned_stop_ns`` holds all planned time, its ``buckets`` tell the changeover apart."""
    changeover = bucket_ns(s.buckets, CHANGEOVER)
    out = {k: changeover if k == CHANGEOVER else int(getattr(s, f"{k}_ns")) for k in TIMES}
    out[PLANNED] -= changeover
    return out


def total_of(parts: Iterable[Totals]) -> Totals:
    out = Totals()
    for p in parts:
        out.merge(p)
    return out
