"""``packml watch``: a live view of a cell, redrawn on every change."""

from __future__ import annotations

import argparse
import datetime as dt
import sys
import threading
import time
from typing import Any

from ..client import CellProxy, Unavailable
from .main import EXIT_OK, EXIT_UNAVAILABLE, EXIT_USAGE
from .session import add_common, fail, session

RED, YELLOW, GREEN, BOLD, DIM, RESET = (
    "\033[31m",
    "\033[33m",
    "\033[32m",
    "\033[1m",
    "\033[2m",
    "\033[0m",
)
STATE_COLORS = {"EXECUTE": GREEN, "ABORTED": RED, "ABORTING": RED, "STOPPED": YELLOW,
                "HELD": YELLOW, "SUSPENDED": YELLOW, "COMPLETE": GREEN, "IDLE": GREEN}  # fmt: skip


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "watch",
        help="a live view of the cell",
        description="Cell and units with state and mode, EMs, a one-line alarm banner, counters and "
        "timers, redrawn on every change. Ctrl-C quits.",
    )
    p.add_argument(
        "--frames",
        type=int,
        default=0,
        help="stop after this many frames (default: run until Ctrl-C)",
    )
    p.add_argument("--interval", type=float, default=0.1, help="minimum seconds between redraws")
    p.add_argument(
        "--plain",
        action="store_true",
        help="no colours or screen clearing (default when not a terminal)",
    )
    add_common(p)
    p.set_defaults(func=watch)


def hms(seconds: int) -> str:
    h, rest = divmod(int(seconds), 3600)
    return f"{h:02d}:{rest // 60:02d}:{rest % 60:02d}"


def render(cell: CellProxy, color: bool) -> str:
    def c(code: str, text: str) -> str:
        return f"{code}{text}{RESET}" if color else text

    cs = cell.cell_status
    now = dt.datetime.now().strftime("%H:%M:%S")
    head = f"{c(BOLD, cell.cell)}  {cs.state_current_name if cs else ''}  {now}"
    if cs is not None and cs.lost_units:
        head += "  " + c(RED, f"LOST: {', '.join(cs.lost_units)}")
    if cs is not None and cs.busy:
        head += "  " + c(YELLOW, f"sequence: {cs.sequence_step}")
    lines = [head]
    banners = [
        f"{u.name}: {u.status.alarm_banner}"
        for u in cell.units.values()
        if u.status and u.status.alarm_banner
    ]
    lines.append(c(RED, "  " + " | ".join(banners)) if banners else c(DIM, "  no active alarm"))
    lines.append(
        f"  {'UNIT':<14}{'STATE':<14}{'MODE':<13}{'EMS':<6}{'PROCESSED':>10}{'DEFECTIVE':>10}  {'IN STATE':>9}  {'IN MODE':>9}"
    )
    for u in cell.units.values():
        st, ad = u.status, u.admin
        if st is None:
            lines.append(f"  {u.name:<14}{c(DIM, 'no status')}")
            continue
        online = sum(e.online for e in st.equipment_modules)
        processed = sum(x.count for x in ad.prod_processed_count) if ad else 0
        defective = sum(x.count for x in ad.prod_defective_count) if ad else 0
        in_state = ad.state_current_time[st.unit_mode_current * 18 + st.state_current] if ad else 0
        in_mode = ad.mode_current_time[st.unit_mode_current] if ad else 0
        state = c(STATE_COLORS.get(st.state_current_name, ""), f"{st.state_current_name:<14}")
        lines.append(
            f"  {u.name:<14}{state}{st.unit_mode_current_name:<13}{online}/{len(st.equipment_modules):<4}"
            f"{processed:>10}{defective:>10}  {hms(in_state):>9}  {hms(in_mode):>9}"
        )
        ems = []
        for e in st.equipment_modules:
            mark = "✓" if e.state_complete else ("●" if e.online else "○")
            text = f"{e.name} {mark}" + ("" if e.active else " (inactive)")
            ems.append(c(RED, text) if e.active and not e.online else text)
        if ems:
            lines.append("      " + "  ".join(ems))
        if st.mode_change_not_allowed:
            lines.append("      " + c(RED, "MODE CHANGE NOT ALLOWED"))
    recent = sorted(
        (t for u in cell.units.values() for t in u.transitions[-4:]),
        key=lambda t: (t.stamp.sec, t.stamp.nanosec),
    )[-5:]
    if recent:
        lines.append("  last transitions:")
        for t in recent:
            when = dt.datetime.fromtimestamp(t.stamp.sec).strftime("%H:%M:%S")
            what = (
                f"{t.from_state_name} -> {t.to_state_name}"
                if t.from_state != t.to_state
                else f"mode {t.from_mode} -> {t.to_mode}"
            )
            lines.append(
                f"    {when} {t.unit:<14}{what} ({t.trigger_name.lower()}{', ' + t.source if t.source and t.source != 'unit' else ''})"
            )
    lines.append(c(DIM, "  ● online  ○ offline  ✓ state complete      Ctrl-C quits"))
    return "\n".join(lines)


def watch(args: argparse.Namespace) -> int:
    plain = args.plain or not sys.stdout.isatty()
    changed = threading.Event()
    with session(args) as s:
        try:
            cell = s.cell()
        except LookupError as exc:
            return fail(str(exc), EXIT_USAGE)
        except Unavailable as exc:
            return fail(str(exc), EXIT_UNAVAILABLE)

        def on_change(*_: Any) -> None:
            changed.set()

        cell.on_change = on_change
        for u in cell.units.values():
            u.on_change = on_change
        frames = 0
        last = 0.0
        changed.set()
        try:
            while not args.frames or frames < args.frames:
                if not changed.wait(1.0):
                    pass  # redraw at least every second (clock, timers)
                changed.clear()
                wait = args.interval - (time.monotonic() - last)
                if wait > 0:
                    time.sleep(wait)
                frame = render(cell, color=not plain)
                last = time.monotonic()
                if plain:
                    print(frame + "\n", flush=True)
                else:
                    sys.stdout.write("\033[H\033[2J" + frame + "\n")
                    sys.stdout.flush()
                frames += 1
        except KeyboardInterrupt:
            pass
    return EXIT_OK
