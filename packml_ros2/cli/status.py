"""``packml status [unit]``: one line per unit, or everything about one unit."""

from __future__ import annotations

import argparse
import threading
import time
from collections.abc import Mapping

from packml_interfaces.msg import CellStatus

from ..client import CellProxy, Unavailable, UnitProxy
from .main import EXIT_UNAVAILABLE, EXIT_USAGE
from .session import add_common, fail, session


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "status",
        help="states, modes, EMs, alarms and counts",
        description="Without a unit: one line per unit of the cell. With a unit "
        "(name, cell/unit or /cell/unit): its status, EMs, alarms, counters and times.",
    )
    p.add_argument("unit", nargs="?", help="a unit (default: every unit of the cell)")
    add_common(p)
    p.set_defaults(func=status)


def status(args: argparse.Namespace) -> int:
    with session(args, topics=("status", "admin")) as s:
        try:
            if args.unit:
                unit = s.unit(args.unit)
                unit.wait_status(timeout=s.timeout)
                unit.wait_admin(timeout=s.timeout)  # latched too: counters, times, OEE
                print(detail(unit))
                return 0
            cell = s.cell()
            if not cell.units:
                return fail(f"no unit found in cell {cell.cell}", EXIT_UNAVAILABLE)
            lost = wait_cell(cell, s.timeout)
            print(table(cell.cell, list(cell.units.values()), cell.cell_status, lost), flush=True)
            if lost:
                return fail("; ".join(f"{u}: {why}" for u, why in lost.items()), EXIT_UNAVAILABLE)
            return 0
        except LookupError as exc:
            return fail(str(exc), EXIT_USAGE)
        except Unavailable as exc:
            return fail(str(exc), EXIT_UNAVAILABLE)


def lost_units(cell: CellProxy) -> dict[str, str]:
    """The units the coordinator's cell status reports lost: name -> why. (A unit it has not
    seen yet, just after its start, is not online but not lost either: it is waited for.)"""
    cs = cell.cell_status
    if cs is None:
        return {}
    return dict.fromkeys(cs.lost_units, "lost (the coordinator has no sign of life from it)")


def wait_cell(cell: CellProxy, timeout: float) -> dict[str, str]:
    """Wait until every unit's status (and admin data, if its proxy follows it) arrived, or the
    coordinator reports the unit lost (then it is not waited for: a killed unit or a frozen PLC
    never answers); at the latest after ``timeout``. Returns the units without an answer or
    lost: name -> why."""
    changed = threading.Event()
    cell.on_change = lambda *_: changed.set()
    for u in cell.units.values():
        u.on_change = cell.on_change
    deadline = time.monotonic() + timeout
    again_at = deadline - timeout / 2  # a unit's writer on the graph, nothing came: subscribe again
    while True:
        changed.clear()
        lost = lost_units(cell)
        waiting = [
            u
            for u in cell.units.values()
            if u.name not in lost
            and (u.status is None or ("admin" in u.topics and u.admin is None))
        ]
        remaining = deadline - time.monotonic()
        if not waiting or remaining <= 0:
            break
        if time.monotonic() >= again_at:
            again_at = float("inf")
            for unit in waiting:
                unit.hear_again("status", "admin")
        changed.wait(min(remaining, 0.25))  # (a lease the coordinator ends sends a cell status)
    lost = lost_units(cell)
    return {
        u.name: lost.get(u.name, f"no status within {timeout:g} s ({_writers(u)})")
        for u in cell.units.values()
        if u.status is None or u.name in lost
    }


def _writers(unit: UnitProxy) -> str:
    """Why a unit's status may not have come: whether its status writer is on the graph and
    matched (none on the graph: the unit is not reachable; on it but not matched: discovery
    went one way)."""
    graph = unit.node.count_publishers(f"{unit.path}/status")
    if not graph:
        return "not reachable: no status writer on the graph"
    return f"its status writer is on the graph, {unit.publishers('status')} matched"


def counts(unit: UnitProxy) -> str:
    a = unit.admin
    if a is None:
        return ""
    processed = sum(c.count for c in a.prod_processed_count)
    defective = sum(c.count for c in a.prod_defective_count)
    return f"{processed} processed, {defective} defective"


def table(
    cell: str,
    units: list[UnitProxy],
    cell_status: CellStatus | None = None,
    lost: Mapping[str, str] | None = None,
) -> str:
    """One row per unit; a unit in ``lost`` (name -> why) is marked LOST, with what the
    coordinator last knew of it (or its own last status) on a line below the table."""
    lost = lost or {}
    summaries = {u.name: u for u in cell_status.units} if cell_status is not None else {}
    rows = [("UNIT", "STATE", "MODE", "SEQ", "EMS", "ALARMS", "COUNTS")]
    notes = []
    for u in units:
        st = u.status
        if u.name in lost:
            last = st or summaries.get(u.name)
            was = f"last seen in {last.state_current_name}" if last is not None else "never seen"
            notes.append(f"  LOST {u.name}: {lost[u.name]}; {was}")
        if st is None:
            rows.append((u.name, "LOST", "-", "-", "-", "-", "-"))
            continue
        online = sum(e.online for e in st.equipment_modules)
        alarms = st.alarm_banner or (f"{st.active_alarms} active" if st.active_alarms else "-")
        state = f"LOST ({st.state_current_name})" if u.name in lost else st.state_current_name
        rows.append(
            (
                u.name,
                state,
                st.unit_mode_current_name,
                str(st.sequence),
                f"{online}/{len(st.equipment_modules)}",
                alarms,
                counts(u) or "-",
            )
        )
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]) - 1)]
    head = f"cell {cell}" + (
        f": {cell_status.state_current_name}" if cell_status is not None else ""
    )
    if lost:
        head += f"  LOST: {', '.join(lost)}"
    lines = [head]
    for r in rows:
        lines.append(
            "  " + "  ".join(c.ljust(w) for c, w in zip(r[:-1], widths, strict=True)) + "  " + r[-1]
        )
    return "\n".join(lines + notes)


def detail(unit: UnitProxy) -> str:
    st = unit.status
    assert st is not None
    lines = [
        f"{unit.path}: {st.state_current_name} ({st.state_current}) in {st.unit_mode_current_name} ({st.unit_mode_current}), sequence {st.sequence}",
        f"  valid now: {', '.join(n.lower() for n in st.commands_valid_names) or 'none'}",
    ]
    if st.state_change_in_process:
        lines.append(f"  heading for {st.state_requested}")
    if st.unit_mode_change_in_process:
        lines.append(f"  mode change to {st.unit_mode_requested} in process")
    if st.mode_change_not_allowed:
        lines.append("  MODE CHANGE NOT ALLOWED")
    lines.append(
        f"  speed {st.mach_speed:g} (actual {st.cur_mach_speed:g}); remote commands {'on' if st.remote_commands_enabled else 'off'}"
    )
    if st.equipment_interlock.blocked or st.equipment_interlock.starved:
        lines.append(
            f"  interlock: {'BLOCKED ' if st.equipment_interlock.blocked else ''}{'STARVED' if st.equipment_interlock.starved else ''}"
        )
    if st.equipment_modules:
        lines.append("  equipment modules:")
        for e in st.equipment_modules:
            flags = [("online" if e.online else "OFFLINE"), ("active" if e.active else "inactive")]
            if e.state_complete:
                flags.append("done")
            lines.append(f"    {e.name:<12} {', '.join(flags)}")
    lines.append(
        f"  alarms: {st.alarm_banner or 'none active'} ({st.unacknowledged_alarms} unacknowledged)"
    )
    a = unit.admin
    if a is not None:
        for title, arr in (
            ("consumed", a.prod_consumed_count),
            ("processed", a.prod_processed_count),
            ("defective", a.prod_defective_count),
        ):
            for c in arr:
                if c.name or c.count or c.acc_count:
                    lines.append(
                        f"  {title:<9} [{c.id}] {c.name or '-'}: {c.count} {c.unit} (lifetime {c.acc_count})"
                    )
        mode = st.unit_mode_current
        lines.append(
            f"  time in {st.unit_mode_current_name}: {a.mode_current_time[mode]} s now, {a.mode_cumulative_time[mode]} s in all; since reset {a.acc_time_since_reset} s"
        )
        if a.stop_reason_extent:
            lines.append(f"  stop reason: {a.stop_reason.id} {a.stop_reason.message}")
        o = a.oee
        lines.append(
            f"  OEE {o.oee:.1%} (availability {o.availability:.1%}, performance {o.performance:.1%}, quality {o.quality:.1%})"
        )
    return "\n".join(lines)
