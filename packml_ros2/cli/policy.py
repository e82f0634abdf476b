"""``packml policy <cell.yaml>``: the SROS2 permission policy of a cell (:mod:`packml_ros2.policy`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..core import ConfigError
from .main import EXIT_USAGE


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "policy",
        help="the SROS2 permission policy of a cell",
        description="Write the SROS2 access-control policy (sros2 format 0.2.0) of a cell: one "
        "enclave per unit, EM and the coordinator with exactly the names it serves, publishes and "
        "subscribes, and enclaves for the faces (hmi, opcua, operator). Feed it to "
        "`ros2 security create_permission <keystore> <enclave> <file>` where the middleware has "
        "DDS Security.",
    )
    p.add_argument("cell_file", help="the cell file")
    p.add_argument("-o", "--output", help="write here (default: standard output)")
    p.set_defaults(func=policy)


def policy(args: argparse.Namespace) -> int:
    from .. import launcher
    from ..policy import endpoints, policy_xml

    try:
        plan = launcher.plan(args.cell_file)
    except ConfigError as exc:
        print(exc.prefixed("packml policy"), file=sys.stderr)
        return EXIT_USAGE
    enclaves = endpoints(plan)
    text = policy_xml(enclaves)
    if args.output is None:
        sys.stdout.write(text)
    else:
        Path(args.output).write_text(text, encoding="utf-8")
        print(f"{args.output}: {len(enclaves)} enclaves of cell {plan.cell.cell}")
    return 0
