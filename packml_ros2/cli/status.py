"""``packml status [unit]``: one line per unit, or everything about one unit."""

from __future__ import annotations

import argparse

from ..client import Unavailable, UnitProxy
from .main import EXIT_UNAVAILABLE, EXIT_USAGE
from .session import add_common, fail, session


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = subparsers.add_parser("status", help="states, modes, EMs, alarms and counts",
                              description="Without a unit: one line per unit of the cell. With a unit "
                              "(name, cell/unit or /cell/unit): its status, EMs, alarms, counters and times.")  # fmt: skip
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
            for unit in cell.units.values():
                unit.wait_status(timeout=s.timeout)
                unit.wait_admin(timeout=s.timeout)  # the counts
            print(table(cell.cell, list(cell.units.values()), cell.cell_status))
            return 0
        except LookupError as exc:
            return fail(str(exc), EXIT_USAGE)
        except Unavailable as exc:
            return fail(str(exc), EXIT_UNAVAILABLE)


def counts(unit: UnitProxy) -> str:
    a = unit.admin
    if a is None:
        return ""
    processed = sum(c.count for c in a.prod_processed_count)
    defective = sum(c.count for c in a.prod_defective_count)
    return f"{processed} processed, {defective} defective"


def table(cell: str, units: list[UnitProxy], cell_status: object | None = None) -> str:
    rows = [("UNIT", "STATE", "MODE", "SEQ", "EMS", "ALARMS", "COUNTS")]
    for u in units:
        st = u.status
        assert st is not None
        online = sum(e.online for e in st.equipment_modules)
        alarms = st.alarm_banner or (f"{st.active_alarms} active" if st.active_alarms else "-")
        rows.append((u.name, st.state_current_name, st.unit_mode_current_name, str(st.sequence),
                     f"{online}/{len(st.equipment_modules)}", alarms, counts(u) or "-"))  # fmt: skip
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]) - 1)]
    lines = [
        f"cell {cell}" + (f": {cell_status.state_current_name}" if cell_status is not None else "")
    ]  # type: ignore[attr-defined]
    for r in rows:
        lines.append(
            "  " + "  ".join(c.ljust(w) for c, w in zip(r[:-1], widths, strict=True)) + "  " + r[-1]
        )
    return "\n".join(lines)


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
