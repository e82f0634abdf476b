"""``packml doctor [cell.yaml]``: check this host for running PackML cells over DDS, and say what
to change (discovery settings, domain, Fast DDS profile, participants against the ~100 per host
limit, shared memory, clock). No ROS import: it answers on a host where ROS itself misbehaves."""

from __future__ import annotations

import argparse
import sys

from ..doctor import CellSize, Report, diagnose, read_host
from .main import EXIT_USAGE

EXIT_FINDINGS = 1  # something to change (a warning or a failure); 0: nothing


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "doctor",
        help="check this host's DDS setup and say what to change",
        description="Checks this host for PackML cells over DDS: discovery settings, ROS "
        "domain, Fast DDS profile, DDS participants against the ~100 per host limit, shared "
        "memory, clock. With a cell file, counts what the cell adds. Exit 0: nothing to "
        "change; 1: something to change.",
    )
    p.add_argument("cell_file", nargs="?", help="a cell file whose participants to count in")
    p.add_argument("--json", action="store_true", help="print the findings as JSON")
    p.set_defaults(func=doctor)


def cell_size(path: str) -> CellSize:
    from ..core import load_cell

    cell = load_cell(path)
    ems = sum(len(u.equipment_modules) for u in cell.units.values())
    coordinator = 1 if cell.coordinator.enabled else 0
    return CellSize(cell.cell, len(cell.units), ems, len(cell.units) + ems + coordinator)


def render(report: Report) -> str:
    marks = {"ok": "ok  ", "warn": "WARN", "fail": "FAIL"}
    lines = []
    for f in report.findings:
        lines.append(f"{marks[f.level]}  {f.check}: {f.finding}")
        if f.change:
            lines.append(f"      -> {f.change}")
    lines.append(
        "nothing to change" if report.worst == "ok" else "something to change (see -> above)"
    )
    return "\n".join(lines)


def doctor(args: argparse.Namespace) -> int:
    cell = None
    if args.cell_file:
        from ..core import ConfigError

        try:
            cell = cell_size(args.cell_file)
        except (ConfigError, OSError) as exc:
            print(f"packml doctor: {exc}", file=sys.stderr)
            return EXIT_USAGE
    report = diagnose(read_host(), cell)
    print(report.to_json() if args.json else render(report))
    return 0 if report.worst == "ok" else EXIT_FINDINGS
