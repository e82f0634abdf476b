"""``packml``: run and operate PackML cells without the ros2 command line.

    packml launch config/demo_cell.yaml      start a whole cell (units, EMs, coordinator)
    packml status [unit]                     states, modes, EMs, alarms, counters
    packml cmd <unit|cell> <command>         reset, start, stop, hold, ... (names or numbers)
    packml mode <unit|cell> <mode>           production, maintenance, manual, ... (or numbers)
    packml alarms [list|ack|reset] [unit]    the alarm list, acknowledge, reset
    packml watch                             a live view of the cell
    packml fault <unit>/<em> <fault> on|off  switch a simulated fault
    packml record / replay                   rosbag2 recordings as regression tests
    packml hmi <cell.yaml>                   the operator HMI in a browser
    packml opcua <cell.yaml>                 the cell as OPC UA (OPC 30050) objects
    packml mqtt <cell.yaml>                  the cell as a Sparkplug B edge node on a broker
    packml conform </cell/unit|opc.tcp://..>  certify a unit or an OPC 30050 PLC against the standard
    packml policy <cell.yaml>                the SROS2 permission policy of the cell
    packml report [cell]                     the line's losses, OEE and stop episodes
    packml doctor [cell.yaml]                check this host's DDS setup, say what to change
    packml new em <name>                     an equipment-module package (the EM kit)

Exit codes: 0 done, 1 refused by the unit (the reason is printed), 2 usage or configuration
error, 3 a unit or service did not answer (``packml status`` still prints the cell, the lost units
marked).
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

#: Modules registering verbs, in help order; each has ``register(subparsers)``; and its verbs.
VERB_MODULES = {
    "launch": ("launch",),
    "status": ("status",),
    "control": ("cmd", "mode", "fault"),
    "recipe": ("recipe",),
    "alarms": ("alarms",),
    "watch": ("watch",),
    "bag": ("record", "replay"),
    "hmi": ("hmi",),
    "opcua": ("opcua",),
    "mqtt": ("mqtt",),
    "conform": ("conform",),
    "policy": ("policy",),
    "report": ("report",),
    "doctor": ("doctor",),
    "new": ("new",),
}

EXIT_OK, EXIT_REFUSED, EXIT_USAGE, EXIT_UNAVAILABLE = 0, 1, 2, 3


def build_parser(verb: str | None = None) -> argparse.ArgumentParser:
    """The parser of every verb, or with ``verb`` only of the module that registers it (a verb
    does not import what the others need: ``packml status`` starts sooner)."""
    parser = argparse.ArgumentParser(
        prog="packml",
        description="Run and operate PackML (ISA-TR88.00.02) cells on ROS 2.",
        epilog="packml <verb> --help shows the options of each verb.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    subparsers = parser.add_subparsers(dest="verb", metavar="<verb>")
    owners = [m for m, verbs in VERB_MODULES.items() if verb in verbs]
    for name in owners or VERB_MODULES:
        try:
            module = importlib.import_module(f"packml_ros2.cli.{name}")
        except ModuleNotFoundError as exc:
            if exc.name and exc.name.startswith("packml_ros2.cli."):
                continue  # a verb module that is not part of this installation
            raise
        module.register(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    given = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(given[0] if given else None)
    args = parser.parse_args(given)
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_USAGE if args.verb is None and argv else EXIT_OK
    try:
        return int(args.func(args))
    except KeyboardInterrupt:
        return EXIT_OK
    except BrokenPipeError:  # `packml status | head`: the reader left; nothing to report
        sys.stderr.close()
        return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
