"""``packml alarms [list|ack|reset] [unit]``: the alarm list, acknowledge, reset.

The unit may come first and the action be left out, as people type it: ``packml alarms robot_cell``,
``packml alarms --history robot_cell``, ``packml alarms robot_cell ack``."""

from __future__ import annotations

import argparse
import datetime as dt
from concurrent.futures import ThreadPoolExecutor

from packml_interfaces.msg import Alarm
from packml_interfaces.srv import QueryAlarms

from ..client import Unavailable, UnitProxy
from ..core.alarms import select
from .main import EXIT_OK, EXIT_REFUSED, EXIT_UNAVAILABLE, EXIT_USAGE
from .session import add_common, fail, session

STATES = {
    Alarm.ACTIVE_UNACKNOWLEDGED: "ACTIVE",
    Alarm.INACTIVE_UNACKNOWLEDGED: "cleared",
    Alarm.ACKNOWLEDGED: "acked",
}
ACTIONS = ("list", "ack", "reset")
SORTS = {"time": QueryAlarms.Request.SORT_TIME, "category": QueryAlarms.Request.SORT_CATEGORY_TIME,
         "newest": QueryAlarms.Request.SORT_TIME_NEWEST}  # fmt: skip


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "alarms",
        help="list, acknowledge or reset alarms",
        description="list (default): alarms and warnings of a unit or of every unit; ack: "
        "acknowledge (all, or --id/--value); reset: clear latched alarms that are no longer active.",
    )
    p.add_argument(
        "action",
        nargs="?",
        default="list",
        metavar="{list,ack,reset}",
        help="what to do (default list); the unit may also come first",
    )
    p.add_argument("unit", nargs="?", help="a unit (default: every unit of the cell)")
    p.add_argument("--id", type=int, help="ack: only this alarm ID")
    p.add_argument("--value", type=int, default=0, help="ack: the alarm's Value (default 0)")
    p.add_argument(
        "--active", action="store_true", help="list: only alarms whose condition is active"
    )
    p.add_argument("--category", type=int, help="list: only this category (0..9)")
    p.add_argument("--history", action="store_true", help="list: the history ring (newest first)")
    p.add_argument("--sort", choices=list(SORTS), default="time", help="list: order (default time)")
    p.add_argument(
        "--first-out", action="store_true", help="reset: also clear the first-out alarms"
    )
    p.add_argument("--source", default="operator")
    add_common(p)
    p.set_defaults(func=alarms)


def words(args: argparse.Namespace) -> str | None:
    """Put the positional words in order (``robot_cell ack`` is ``ack robot_cell``, a lone unit
    lists); the usage error when they are not an action and a unit."""
    if args.action in ACTIONS:
        return None
    if args.unit is not None and args.unit not in ACTIONS:
        return (
            f"alarms: neither {args.action!r} nor {args.unit!r} is one of {', '.join(ACTIONS)}"
            " (packml alarms [ACTION] [UNIT])"
        )
    args.action, args.unit = args.unit or "list", args.action
    return None


def alarms(args: argparse.Namespace) -> int:
    refused = words(args)
    if refused:
        return fail(refused, EXIT_USAGE)
    # the current list is on the units' latched alarms topic: no service round trip (only the
    # history, and a list longer than the topic holds, ask query_alarms)
    latched = args.action == "list" and not args.history
    with session(args, topics=("alarms",) if latched else ()) as s:
        try:
            units: list[UnitProxy] = (
                [s.unit(args.unit)] if args.unit else list(s.cell().units.values())
            )
            if not units:
                return fail("no unit found", EXIT_UNAVAILABLE)
            handler = (
                _listed if latched else {"list": _list, "ack": _ack, "reset": _reset}[args.action]
            )
            # every unit at once (one service round trip, not one per unit), printed in order
            with ThreadPoolExecutor(max_workers=len(units)) as pool:
                answers = list(pool.map(lambda u: handler(u, args, s.timeout), units))
            for text, _ in answers:
                print(text)
            return max(code for _, code in answers)
        except LookupError as exc:
            return fail(str(exc), EXIT_USAGE)
        except Unavailable as exc:
            return fail(str(exc), EXIT_UNAVAILABLE)


def _when(a: Alarm) -> str:
    return (
        dt.datetime.fromtimestamp(a.stamp.sec + a.stamp.nanosec * 1e-9).strftime("%H:%M:%S")
        if a.stamp.sec
        else "-"
    )


def _view(a: Alarm) -> tuple[bool, int, float]:
    return a.trigger, a.category, a.stamp.sec + a.stamp.nanosec * 1e-9


def _listed(u: UnitProxy, args: argparse.Namespace, timeout: float) -> tuple[str, int]:
    """The current alarms and warnings from the unit's latched ``alarms`` topic, filtered and
    ordered as ``query_alarms`` would; a list that overflowed the topic is asked for instead."""
    msg = u.wait_alarms(timeout)
    if msg.alarm_overflow or msg.warning_overflow:
        return _list(u, args, timeout)
    listed = select([*msg.alarms, *msg.warnings], args.active, args.category, args.sort, _view)
    return _lines(u.name, listed, "alarms"), EXIT_OK


def _list(u: UnitProxy, args: argparse.Namespace, timeout: float) -> tuple[str, int]:
    resp = u.call_sync(
        "query_alarms",
        timeout,
        active_only=args.active,
        filter_category=args.category is not None,
        category=args.category or 0,
        include_warnings=True,
        history=args.history,
        sort=SORTS["newest" if args.history and args.sort == "time" else args.sort],
    )
    return _lines(u.name, resp.alarms, "history" if args.history else "alarms"), EXIT_OK


def _lines(unit: str, alarms: list[Alarm], what: str) -> str:
    if not alarms:
        return f"{unit}: no {what}"
    lines = [f"{unit}:"]
    for a in alarms:
        kind = {
            Alarm.KIND_WARNING: "warning",
            Alarm.KIND_EVENT: "event",
            Alarm.KIND_COMMAND: "command",
        }.get(a.kind, "alarm")
        where = f" [{a.em}]" if a.em else ""
        state = (
            STATES.get(a.operator_state, "?")
            if a.kind in (Alarm.KIND_ALARM, Alarm.KIND_WARNING)
            else ""
        )
        lines.append(
            f"  {_when(a)}  {a.id:>5}/{a.value:<3} cat {a.category}  {kind:<7} {state:<7} {a.message}{where}"
        )
    return "\n".join(lines)


def _ack(u: UnitProxy, args: argparse.Namespace, timeout: float) -> tuple[str, int]:
    fields = {
        "all": args.id is None,
        "id": args.id or 0,
        "value": args.value,
        "source": args.source,
    }
    resp = u.call_sync("ack_alarms", timeout, **fields)
    ok = resp.accepted or (resp.result == 17 and args.id is None)
    return f"{u.name}: {resp.message}", EXIT_OK if ok else EXIT_REFUSED


def _reset(u: UnitProxy, args: argparse.Namespace, timeout: float) -> tuple[str, int]:
    resp = u.call_sync("reset_alarms", timeout, clear_first_out=args.first_out, source=args.source)
    return f"{u.name}: {resp.message}", EXIT_OK if resp.accepted else EXIT_REFUSED
