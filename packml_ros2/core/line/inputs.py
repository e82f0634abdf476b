"""The line's input log: every input the coordinator gave the line's performance, in order, with
named fields — published on ``<cell>/coordinator/line/input_log`` (``UnitInput``; ``unit`` is the
unit it concerns, ``args_json`` the fields), recorded by ``packml record`` and fed to a fresh
:class:`~.performance.Performance` by ``packml replay`` (:func:`apply` is the one path both use).

Schema 1 (``start`` says ``schema``); times are integer nanoseconds of the line's clock (``t``,
when it was applied) and of the unit's (``time``, its stamp):

==============  ============================================================================
``start``       ``schema``, ``state`` (the open state restored, or null), ``ledger`` (the
                running windows a replay continues: lifetime, since reset, the open shifts,
                the last hour)
``status``      ``unit``, ``sequence``, ``time``, ``state``, ``mode``, ``stop_reason_id``,
                ``blocked``, ``starved``
``transition``  ``unit``, ``sequence``, ``time``, ``from_state``, ``to_state``, ``from_mode``,
                ``to_mode``, ``trigger``, ``command``, ``source``, ``detail``
``admin``       ``unit``, ``time``, ``processed``, ``defective`` (AccCount totals),
                ``stop_reason`` (id, value, message, category, source, em, time) or null
``online``      ``unit``
``lost``        ``unit``, ``why``
``cell``        ``command``, ``caller``: a cell command begins
``interlock``   ``unit``, ``active``, ``reason``: the coordinator sets or clears one
``reset``       the since-reset window begins
``tick``        the clock moved (losses are published)
==============  ============================================================================
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from .performance import Performance, StatusSnap, TransitionSnap

SCHEMA = 1
START, STATUS, TRANSITION, ADMIN = "start", "status", "transition", "admin"
ONLINE, LOST, CELL, INTERLOCK, RESET, TICK = "online", "lost", "cell", "interlock", "reset", "tick"
NAMES = (START, STATUS, TRANSITION, ADMIN, ONLINE, LOST, CELL, INTERLOCK, RESET, TICK)


def ns(stamp: Any) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


# -- from messages (read by attribute: rclpy messages, or anything alike) --------------------------
def status_fields(unit: str, s: Any) -> dict[str, Any]:
    ems = [e for e in s.equipment_modules if e.active]
    return {
        "unit": unit,
        "sequence": int(s.sequence),
        "time": ns(s.stamp),
        "state": int(s.state_current),
        "mode": int(s.unit_mode_current),
        "stop_reason_id": int(s.stop_reason_id),
        "blocked": any(e.blocked for e in ems),
        "starved": any(e.starved for e in ems),
    }


def transition_fields(unit: str, t: Any) -> dict[str, Any]:
    return {
        "unit": unit,
        "sequence": int(t.sequence),
        "time": ns(t.stamp),
        "from_state": int(t.from_state),
        "to_state": int(t.to_state),
        "from_mode": int(t.from_mode),
        "to_mode": int(t.to_mode),
        "trigger": int(t.trigger),
        "command": int(t.command),
        "source": str(t.source),
        "detail": str(t.detail),
    }


def admin_fields(unit: str, a: Any) -> dict[str, Any]:
    reason = None
    if a.stop_reason_extent:
        r = a.stop_reason
        reason = {
            "id": int(r.id),
            "value": int(r.value),
            "message": str(r.message),
            "category": int(r.category),
            "source": str(r.source),
            "em": str(r.em),
            "time": ns(r.stamp),
        }
    return {
        "unit": unit,
        "time": ns(a.stamp),
        "processed": sum(int(c.acc_count) for c in a.prod_processed_count),
        "defective": sum(int(c.acc_count) for c in a.prod_defective_count),
        "stop_reason": reason,
    }


# -- applying --------------------------------------------------------------------------------------
def _status(p: Performance, t: int, f: Mapping[str, Any]) -> None:
    p.status(
        t,
        f["unit"],
        StatusSnap(
            int(f["sequence"]),
            int(f["time"]),
            int(f["state"]),
            int(f["mode"]),
            int(f["stop_reason_id"]),
            bool(f["blocked"]),
            bool(f["starved"]),
        ),
    )


def _transition(p: Performance, t: int, f: Mapping[str, Any]) -> None:
    p.transition(
        t,
        f["unit"],
        TransitionSnap(
            int(f["sequence"]),
            int(f["time"]),
            int(f["from_state"]),
            int(f["to_state"]),
            int(f["from_mode"]),
            int(f["to_mode"]),
            int(f["trigger"]),
            int(f["command"]),
            str(f["source"]),
            str(f["detail"]),
        ),
    )


def _admin(p: Performance, t: int, f: Mapping[str, Any]) -> None:
    p.admin(
        t, f["unit"], int(f["time"]), int(f["processed"]), int(f["defective"]), f.get("stop_reason")
    )


APPLY: Mapping[str, Callable[[Performance, int, Mapping[str, Any]], None]] = {
    STATUS: _status,
    TRANSITION: _transition,
    ADMIN: _admin,
    ONLINE: lambda p, t, f: p.online(t, f["unit"]),
    LOST: lambda p, t, f: p.lost(t, f["unit"], str(f.get("why", ""))),
    CELL: lambda p, t, f: p.cell_command(t, int(f["command"]), str(f["caller"])),
    INTERLOCK: lambda p, t, f: p.interlock(t, f["unit"], bool(f["active"]), str(f["reason"])),
    RESET: lambda p, t, f: p.reset(t),
    TICK: lambda p, t, f: p.tick(t),
}


def apply(p: Performance, name: str, t: int, fields: Mapping[str, Any]) -> None:
    """Apply one input (not ``start``); KeyError/ValueError/TypeError for a malformed one."""
    if "unit" in fields and fields["unit"] not in p.trackers:
        raise KeyError(f"no unit {fields['unit']!r} in this line")
    APPLY[name](p, t, fields)
