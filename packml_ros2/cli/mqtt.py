"""``packml mqtt <cell.yaml>``: the cell as a Sparkplug B edge node (each unit a device) on the
MQTT broker of its ``mqtt:`` block."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..core import ConfigError
from .main import EXIT_USAGE


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "mqtt",
        help="publish the cell's units to an MQTT broker (Sparkplug B, optional UNS JSON)",
        description="A Sparkplug B edge node for the units of a cell file, configured by its "
        "mqtt: block (default broker 127.0.0.1:1883, group packml, edge node = the cell): "
        "births, data on change, deaths, and DCMD commands answered in each unit's "
        "Command/Answer metrics. Ctrl-C stops it (with an NDEATH).",
    )
    p.add_argument("cell_file", type=Path, help="the cell YAML (e.g. config/demo_cell.yaml)")
    p.add_argument("--host", help="the broker's address (overrides mqtt.host)")
    p.add_argument("--port", type=int, help="the broker's port (overrides mqtt.port)")
    p.add_argument("--check", action="store_true", help="only validate the configuration")
    p.set_defaults(func=mqtt)


def mqtt(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from ..core import load_cell
    from ..mqtt.config import parse_mqtt

    try:
        cell = load_cell(args.cell_file)
        config = parse_mqtt(cell)
    except ConfigError as exc:
        print(exc.prefixed("packml mqtt"), file=sys.stderr)
        return EXIT_USAGE
    if args.host:
        config = replace(config, host=args.host)
    if args.port is not None:
        if not 1 <= args.port <= 65535:
            print(f"packml mqtt: --port {args.port}: expected 1..65535", file=sys.stderr)
            return EXIT_USAGE
        config = replace(config, port=args.port)
    if args.check:
        print(
            f"{args.cell_file}: mqtt block valid ({config.host}:{config.port}, "
            f"{config.topic('NBIRTH')}, units: {', '.join(config.units)})"
        )
        return 0
    import logging

    from .. import run
    from ..mqtt.node import MqttFace

    run.cell_environment(cell.discovery, tool=True)
    run.default_environment(tool=True)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    return MqttFace(cell, config, ready=lambda text: print(text, flush=True)).run()
