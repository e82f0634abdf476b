"""The line's views (:mod:`packml_ros2.core.line`) as ``packml_interfaces`` messages, and those
messages as plain dicts (JSON for ``packml report`` and the HMI). One conversion, used by the
coordinator node, the replay and the faces."""

from __future__ import annotations

import math
from typing import Any

from builtin_interfaces.msg import Time
from packml_interfaces.msg import (
    Alarm,
    LineDeparture,
    LineEpisode,
    LineLosses,
    LossBucket,
    LossScope,
)

from .core.line.line import EpisodeView, LossesView
from .core.line.losses import Summary, times_ns
from .core.numbers import state_name

NS = 1_000_000_000
UNKNOWN_TRIGGER = 255


MAX_STAMP = (2**31 - 1) * NS + NS - 1  #: builtin_interfaces/Time's sec is an int32


def stamp(ns: int) -> Time:
    """``ns`` since the epoch as a Time, clamped to what a Time can hold (0 .. 2038)."""
    ns = min(max(0, int(ns)), MAX_STAMP)
    return Time(sec=ns // NS, nanosec=ns % NS)


def ns_of(t: Any) -> int:
    return int(t.sec) * NS + int(t.nanosec)


def _i32(x: int) -> int:
    return max(-(2**31), min(2**31 - 1, int(x)))


def episode_msg(view: EpisodeView, cell: str) -> LineEpisode:
    e, root = view.episode, view.root
    end = e.end if e.end is not None else 0
    msg = LineEpisode(
        id=e.id,
        cell=cell,
        start=stamp(e.start),
        end=stamp(end),
        open=e.end is None,
        duration_ns=e.duration(view.now),
        stamp=stamp(view.now if e.end is None else e.end),
        root_unit=root.unit,
        bucket=root.bucket,
        reason=root.reason,
    )
    d = root.departure
    if d is not None:
        msg.source = d.source
        msg.trigger = d.trigger if 0 <= d.trigger < UNKNOWN_TRIGGER else UNKNOWN_TRIGGER
    else:
        msg.trigger = UNKNOWN_TRIGGER
    r = e.stop_reason
    if r:
        msg.stop_reason_known = True
        msg.stop_reason = Alarm(
            trigger=False,
            id=_i32(r.get("id", 0)),
            value=_i32(r.get("value", 0)),
            message=str(r.get("message", "")),
            category=_i32(r.get("category", 0)),
            source=str(r.get("source", "")),
            em=str(r.get("em", "")),
            stamp=stamp(int(r.get("time", 0))),
        )
    for d in sorted(e.departures, key=lambda x: x.time):
        msg.affected.append(
            LineDeparture(
                unit=d.unit,
                stamp=stamp(d.time),
                sequence=max(0, d.sequence),
                to_state=int(d.to_state),
                to_state_name=state_name(d.to_state),
                how=d.kind,
                reason=d.label,
                bucket=d.bucket,
                trigger=d.trigger if 0 <= d.trigger < UNKNOWN_TRIGGER else UNKNOWN_TRIGGER,
                command=int(d.command),
                source=d.source,
                detail=d.detail,
                cause_unit=d.cause_unit,
                stop_reason_id=_i32(d.reason_id),
            )
        )
    return msg


def scope_msg(s: Summary, design: float) -> LossScope:
    """LossScope has no field of its own for the changeover: its ``planned_stop_ns`` holds it
    (all planned time, "other modes"), its ``buckets`` tell it apart (bucket ``changeover``)."""
    return LossScope(
        scope=s.scope,
        elapsed_ns=s.elapsed,
        planned_stop_ns=s.planned + s.changeover,
        unplanned_stop_ns=s.unplanned,
        blocked_ns=s.blocked,
        starved_ns=s.starved,
        held_ns=s.held,
        running_ns=s.running,
        speed_loss_ns=s.speed_loss,
        quality_loss_ns=s.quality_loss,
        productive_ns=s.productive,
        processed=s.processed,
        defective=s.defective,
        mach_design_speed=float(design),
        availability=s.availability,
        performance=math.nan if s.performance is None else s.performance,
        quality=s.quality,
        oee=s.oee,
        buckets=[LossBucket(bucket=b, reason=r, nanoseconds=ns) for b, r, ns in s.buckets],
    )


def losses_msg(view: LossesView, cell: str, now: int, designs: dict[str, float]) -> LineLosses:
    return LineLosses(
        stamp=stamp(now),
        cell=cell,
        window=view.window,
        start=stamp(view.start),
        end=stamp(view.end),
        scopes=[scope_msg(s, designs.get(s.scope, 0.0)) for s in view.scopes],
    )


# -- messages as dicts -----------------------------------------------------------------------------
def _sec(t: Any) -> float | None:
    n = ns_of(t)
    return n / NS if n else None


def episode_dict(m: Any) -> dict[str, Any]:
    return {
        "id": m.id,
        "cell": m.cell,
        "start": _sec(m.start),
        "end": _sec(m.end),
        "open": m.open,
        "duration": m.duration_ns / NS,
        "root_unit": m.root_unit or "cell",
        "bucket": m.bucket,
        "reason": m.reason,
        "source": m.source,
        "trigger": m.trigger,
        "stop_reason": (
            {
                "id": m.stop_reason.id,
                "value": m.stop_reason.value,
                "message": m.stop_reason.message,
                "category": m.stop_reason.category,
                "source": m.stop_reason.source,
                "em": m.stop_reason.em,
            }
            if m.stop_reason_known
            else None
        ),
        "affected": [
            {
                "unit": d.unit,
                "time": _sec(d.stamp),
                "state": d.to_state_name,
                "how": d.how,
                "reason": d.reason,
                "bucket": d.bucket,
                "source": d.source,
                "cause_unit": d.cause_unit,
            }
            for d in m.affected
        ],
    }


def _float(x: float) -> float | None:
    return None if math.isnan(x) or math.isinf(x) else x


def scope_dict(s: Any) -> dict[str, Any]:
    """A LossScope as a dict; a factor with nothing to divide by is None ("no data", not 0 %):
    availability and OEE without planned production time (an empty shift, a window before
    anything was recorded), performance without running time (or without a design speed),
    quality without a count. Times in seconds, and in ``nanoseconds`` (:func:`times_ns`)."""
    planned_production = s.elapsed_ns - s.planned_stop_ns  # (planned_stop_ns: with changeover)
    ns = times_ns(s)

    def factor(x: float, defined: bool) -> float | None:
        return _float(x) if defined else None

    return {
        "scope": s.scope or "line",
        **{k: v / NS for k, v in ns.items()},
        "processed": s.processed,
        "defective": s.defective,
        "mach_design_speed": s.mach_design_speed,
        "availability": factor(s.availability, planned_production > 0),
        "performance": factor(s.performance, s.running_ns > 0),
        "quality": factor(s.quality, s.processed > 0),
        "oee": factor(s.oee, planned_production > 0),
        "buckets": [
            {"bucket": b.bucket, "reason": b.reason, "seconds": b.nanoseconds / NS}
            for b in s.buckets
        ],
        "nanoseconds": ns,
    }


def losses_dict(m: Any) -> dict[str, Any]:
    return {
        "window": m.window,
        "start": _sec(m.start),
        "end": _sec(m.end),
        "stamp": _sec(m.stamp),
        "scopes": [scope_dict(s) for s in m.scopes],
    }
