"""``packml launch <cell.yaml>``: start a whole cell."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..core import ConfigError
from .main import EXIT_USAGE


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "launch",
        help="start a cell: units, simulated EMs, coordinator",
        description="Start every node of a cell file, wait until they answer, print what to try. "
        "Ctrl-C stops everything (exit code 0).",
    )
    p.add_argument("cell_file", type=Path, help="the cell YAML (e.g. config/demo_cell.yaml)")
    p.add_argument(
        "--processes", action="store_true", help="one OS process per node (default: one process)"
    )
    p.add_argument(
        "--threads",
        type=int,
        default=0,
        help="executor threads in one-process mode (default: by node count)",
    )
    p.add_argument(
        "--logs", type=Path, help="with --processes: write each node's output to this directory"
    )
    p.add_argument("--check", action="store_true", help="only validate the cell file and exit")
    p.set_defaults(func=launch)


def launch(args: argparse.Namespace) -> int:
    from .. import launcher

    try:
        plan = launcher.plan(args.cell_file)
    except ConfigError as exc:
        print(f"packml launch: invalid configuration\n{exc}", file=sys.stderr)
        return EXIT_USAGE
    if args.check:
        print(f"{args.cell_file}: valid ({plan.node_count} nodes)")
        return 0
    if args.processes:
        if args.logs:
            args.logs.mkdir(parents=True, exist_ok=True)
        return launcher.launch_processes(plan, ready=_ready, log_dir=args.logs)
    return launcher.launch_in_process(plan, threads=args.threads, ready=_ready)


def _ready(text: str) -> None:
    print(text, flush=True)
