"""``packml report [cell]``: the line's losses, OEE and stop episodes, from the coordinator.

packml report                       the current shift (lifetime without a shift calendar)
packml report --shift previous      the shift before; --shift 2025-06-16 early: that one
packml report --since 2h            the last two hours (also 30min, 90s, 2025-06-16T06:00)
packml report --window lifetime     15min, 1h, reset (since reset_losses), lifetime
packml report --format csv          the loss rows (they add up to each scope's elapsed time)
packml report --format episodes-csv the episodes of the window, one row each (all: up to 1000)
packml report --format json         everything (windows and episodes) as JSON
packml report --episodes 20         the 20 newest episodes in the table (default 10)

CSV times are ISO 8601 with the local UTC offset (2025-06-16T10:31:13.250+02:00), durations
seconds. A factor with nothing to divide by (an empty shift, no running time, no count) is
"no data" (empty in CSV, null in JSON), never 0 %.
"""

from __future__ import annotations

import argparse
import csv
import datetime as dt
import io
import json
import math
import re
import sys
import time
from typing import Any

from .. import line_msgs
from ..client import Unavailable, call_blocking, discover_cells
from ..core.line.losses import TIMES
from .main import EXIT_REFUSED, EXIT_UNAVAILABLE, EXIT_USAGE
from .session import add_common, fail, session

NS = 1_000_000_000
_SPAN = re.compile(r"^(\d+(?:\.\d+)?)\s*(s|sec|min|m|h|d)$")
_UNITS = {"s": 1, "sec": 1, "m": 60, "min": 60, "h": 3600, "d": 86400}
BUCKET_NAMES = {
    "running": "running", "planned_stop": "planned stop", "changeover": "changeover",
    "unplanned_stop": "unplanned stop", "blocked": "blocked", "starved": "starved", "held": "held",
}  # fmt: skip


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "report",
        help="the line's losses, OEE and stop episodes",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "cell_name", nargs="?", metavar="cell", help="the cell (default: the only one running)"
    )
    which = p.add_mutually_exclusive_group()
    which.add_argument(
        "--shift",
        nargs="?",
        const="current",
        metavar="SHIFT",
        help="current (default), previous, or 'YYYY-MM-DD name'",
    )
    which.add_argument(
        "--since", metavar="TIME", help="a span back from now (2h, 30min) or an ISO time"
    )
    which.add_argument(
        "--window", choices=("15min", "1h", "reset", "lifetime"), help="a running window"
    )
    p.add_argument("--until", metavar="TIME", help="with --since: the end (ISO time; default now)")
    p.add_argument("--format", choices=("table", "csv", "episodes-csv", "json"), default="table")
    p.add_argument(
        "--episodes",
        type=int,
        default=None,
        metavar="N",
        help="episodes listed (default 10; episodes-csv: all, up to 1000)",
    )
    add_common(p)
    p.set_defaults(func=report)


def parse_time(text: str, now: float) -> float:
    """Seconds since the epoch of ``2h``, ``30min``, ``90s`` (back from now) or an ISO time
    (local time unless it names its zone)."""
    m = _SPAN.match(text.strip().lower())
    try:
        t = (
            now - float(m[1]) * _UNITS[m[2]]
            if m
            else dt.datetime.fromisoformat(text.strip()).timestamp()
        )
    except (
        ValueError,
        OverflowError,
    ):  # (a year out of range, or a date out of what a platform's time holds)
        t = math.nan
    if not 0 <= t < 2**31:  # what a ROS Time holds (NaN too): 1970 .. 2038
        raise ValueError(
            f"{text[:60]!r} is not a time between 1970 and 2038: give 2h, 30min, 90s or 2025-06-16T06:00"
        )
    return t


def report(args: argparse.Namespace) -> int:
    from builtin_interfaces.msg import Time
    from packml_interfaces.srv import QueryEpisodes, QueryLosses

    now = time.time()
    request = QueryLosses.Request()
    try:
        if args.since:
            request.window = "since"
            request.since = line_msgs.stamp(int(parse_time(args.since, now) * NS))
            if args.until:
                request.until = line_msgs.stamp(int(parse_time(args.until, now) * NS))
        elif args.until:
            return fail("--until needs --since", EXIT_USAGE)
        elif args.window:
            request.window = args.window
        elif args.shift and args.shift != "current":
            request.window = f"shift:{args.shift}"
        else:
            request.window = "shift"
    except ValueError as exc:
        return fail(str(exc), EXIT_USAGE)
    with session(args) as s:
        try:
            cell = args.cell_name or args.cell
            if not cell:
                cells = discover_cells(s.node, s.timeout)
                if len(cells) != 1:
                    return fail(
                        "no cell running"
                        if not cells
                        else f"several cells are running ({', '.join(cells)}): name one",
                        EXIT_USAGE if cells else EXIT_UNAVAILABLE,
                    )
                cell = next(iter(cells))
            base = f"/{cell}/coordinator/line"
            losses = call_blocking(
                s.node.create_client(QueryLosses, f"{base}/query_losses"),
                request,
                s.timeout,
                f"{base}/query_losses",
            )
            if not losses.accepted and request.window == "shift" and not args.shift:
                request.window = "lifetime"  # no shift calendar (or no shift now)
                losses = call_blocking(
                    s.node.create_client(QueryLosses, f"{base}/query_losses"),
                    request,
                    s.timeout,
                    f"{base}/query_losses",
                )
            if not losses.accepted:
                return fail(f"{cell}: {losses.message}", EXIT_REFUSED)
            window = losses.windows[0]
            wanted = (
                args.episodes
                if args.episodes is not None
                else (1000 if args.format == "episodes-csv" else 10)
            )
            ep_req = QueryEpisodes.Request(limit=max(1, min(wanted, 1000)))
            ep_req.since = window.start if (window.start.sec or window.start.nanosec) else Time()
            ep_req.until = window.end
            episodes = call_blocking(
                s.node.create_client(QueryEpisodes, f"{base}/query_episodes"),
                ep_req,
                s.timeout,
                f"{base}/query_episodes",
            )
        except Unavailable as exc:
            return fail(f"{exc} (is the cell's coordinator running?)", EXIT_UNAVAILABLE)
    data = line_msgs.losses_dict(window)
    eps = [line_msgs.episode_dict(e) for e in episodes.episodes]
    if args.format == "json":
        print(
            json.dumps(
                {"cell": cell, **data, "episodes": eps, "episodes_total": episodes.total}, indent=2
            )
        )
    elif args.format == "csv":
        sys.stdout.write(to_csv(data))
    elif args.format == "episodes-csv":
        sys.stdout.write(episodes_csv(eps))
    else:
        print(table(cell, data, eps, episodes.total))
    return 0


# -- output ----------------------------------------------------------------------------------------
def duration(seconds: float) -> str:
    sign = "-" if seconds < 0 else ""
    seconds = abs(seconds)
    h, rest = divmod(seconds, 3600)
    m, sec = divmod(rest, 60)
    return f"{sign}{int(h)}:{int(m):02d}:{sec:04.1f}"


def percent(x: float | None) -> str:
    return "no data" if x is None or math.isnan(x) else f"{100 * x:.1f}%"


def clock(t: float | None) -> str:
    return dt.datetime.fromtimestamp(t).strftime("%Y-%m-%d %H:%M:%S") if t else "-"


def iso(t: float | None) -> str:
    """ISO 8601, local time with its UTC offset, to the millisecond ('' for none)."""
    if not t:
        return ""
    return dt.datetime.fromtimestamp(t).astimezone().isoformat(timespec="milliseconds")


def affected(e: dict[str, Any]) -> str:
    """The units an episode affected, each once, with how it left Execute each time
    (``robot_cell (internal, propagated)``), in the order they first left."""
    hows: dict[str, list[str]] = {}
    for a in e["affected"]:
        seen = hows.setdefault(a["unit"], [])
        if a["how"] not in seen:
            seen.append(a["how"])
    return ", ".join(f"{unit} ({', '.join(how)})" for unit, how in hows.items())


def rows_of(scope: dict[str, Any]) -> list[tuple[str, str, float]]:
    """(bucket, reason, seconds) rows of a scope: the stops by reason, then the running time as
    speed loss, quality loss and productive time; they add up to its elapsed time."""
    rows = [
        (b["bucket"], b["reason"], b["seconds"])
        for b in scope["buckets"]
        if b["bucket"] != "running"
    ]
    rows += [
        ("speed_loss", "", scope["speed_loss"]),
        ("quality_loss", "", scope["quality_loss"]),
        ("productive", "", scope["productive"]),
    ]
    return rows


def to_csv(data: dict[str, Any]) -> str:
    out = io.StringIO()
    w = csv.writer(out)
    w.writerow(["window", "start", "end", "scope", "bucket", "reason", "seconds"])
    start, end = iso(data["start"]), iso(data["end"])
    for scope in data["scopes"]:
        for bucket, reason, seconds in rows_of(scope):
            w.writerow(
                [data["window"], start, end, scope["scope"], bucket, reason, f"{seconds:.3f}"]
            )
        w.writerow(
            [data["window"], start, end, scope["scope"], "elapsed", "", f"{scope['elapsed']:.3f}"]
        )
    return out.getvalue()


def episodes_csv(episodes: list[dict[str, Any]]) -> str:
    """One row per episode, oldest first; ``end`` empty while it is open."""
    out = io.StringIO()
    w = csv.writer(out)
    w.writerow(
        [
            "id",
            "start",
            "end",
            "seconds",
            "open",
            "root_cause",
            "bucket",
            "reason",
            "source",
            "stop_reason_id",
            "affected",
        ]
    )
    for e in sorted(episodes, key=lambda x: x["id"]):
        reason_id = e["stop_reason"]["id"] if e["stop_reason"] else ""
        w.writerow(
            [
                e["id"],
                iso(e["start"]),
                "" if e["open"] else iso(e["end"]),
                f"{e['duration']:.3f}",
                "yes" if e["open"] else "no",
                e["root_unit"],
                e["bucket"],
                e["reason"],
                e["source"],
                reason_id,
                affected(e),
            ]
        )
    return out.getvalue()


def _grid(rows: list[tuple[str, ...]], right: set[int]) -> list[str]:
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return [
        "  ".join(
            c.rjust(widths[i]) if i in right else c.ljust(widths[i]) for i, c in enumerate(r)
        ).rstrip()
        for r in rows
    ]


def table(cell: str, data: dict[str, Any], episodes: list[dict[str, Any]], total: int) -> str:
    lines = [
        f"line {cell}: {data['window']} ({clock(data['start']) if data['start'] else 'since the first record'} .. {clock(data['end'])})"
    ]
    head = (
        "SCOPE",
        "ELAPSED",
        "PLANNED",
        "CHANGEOVER",
        "UNPLANNED",
        "BLOCKED",
        "STARVED",
        "HELD",
        "RUNNING",
        "SPEED LOSS",
        "QUALITY LOSS",
        "PRODUCTIVE",
        "A",
        "P",
        "Q",
        "OEE",
    )
    rows: list[tuple[str, ...]] = [head]
    for s in data["scopes"]:
        shares = [percent(s[k]) for k in ("availability", "performance", "quality", "oee")]
        rows.append((s["scope"], *(duration(s[k]) for k in TIMES), *shares))
    lines += _grid(rows, set(range(1, len(head))))
    line = data["scopes"][0]
    lines += ["", "LOSSES OF THE LINE (they add up to its elapsed time)"]
    loss_rows: list[tuple[str, ...]] = [("BUCKET", "REASON", "TIME", "SHARE")]
    for bucket, reason, seconds in rows_of(line):
        share = seconds / line["elapsed"] if line["elapsed"] else None
        loss_rows.append(
            (
                BUCKET_NAMES.get(bucket, bucket.replace("_", " ")),
                reason or "-",
                duration(seconds),
                percent(share),
            )
        )
    loss_rows.append(
        (
            "total",
            "",
            duration(sum(r[2] for r in rows_of(line))),
            percent(1.0 if line["elapsed"] else None),
        )
    )
    loss_rows.append(("elapsed", "", duration(line["elapsed"]), ""))
    lines += ["  " + x for x in _grid(loss_rows, {2, 3})]
    lines += ["", f"STOP EPISODES ({len(episodes)} of {total}, newest first)"]
    if episodes:
        ep_rows: list[tuple[str, ...]] = [
            ("#", "START", "DURATION", "ROOT CAUSE", "BUCKET", "REASON", "AFFECTED")
        ]
        for e in episodes:
            dur = duration(e["duration"]) + (" open" if e["open"] else "")
            ep_rows.append(
                (
                    str(e["id"]),
                    clock(e["start"]),
                    dur,
                    e["root_unit"],
                    BUCKET_NAMES.get(e["bucket"], e["bucket"]),
                    e["reason"],
                    affected(e),
                )
            )
        lines += ["  " + x for x in _grid(ep_rows, {0, 2})]
    else:
        lines.append("  none")
    return "\n".join(lines)
