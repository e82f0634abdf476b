"""``packml new em <name>``: a new equipment-module package from the EM kit (:mod:`packml_ros2.kit`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .main import EXIT_USAGE


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "new",
        help="create an equipment-module package (the EM kit)",
        description="Create an ament_python package with an EM class, its entry point, a cell-file "
        "snippet and a pytest test that drives the EM through its states against a real unit "
        "(packml_ros2.testing.em_harness). Build it with colcon; `colcon test` runs the test.",
    )
    p.add_argument("what", choices=["em"], help="what to create: em (an equipment module)")
    p.add_argument("name", help="the package and EM name, e.g. gripper")
    p.add_argument("-d", "--dir", default=".", help="where to create it (default: here)")
    p.set_defaults(func=new)


def new(args: argparse.Namespace) -> int:
    from ..kit import create

    try:
        root = create(args.name, Path(args.dir))
    except (ValueError, OSError) as exc:
        print(f"packml new: {exc}", file=sys.stderr)
        return EXIT_USAGE
    print(
        f"{root}: package {args.name} (EM {args.name}/em.py, cell.yaml, test/test_{args.name}.py)"
    )
    return 0
