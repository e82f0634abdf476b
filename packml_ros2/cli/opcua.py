"""``packml opcua <cell.yaml>``: the cell's units as OPC 30050 objects on an OPC UA server."""

from __future__ import annotations

import argparse
import getpass
import sys
from pathlib import Path

from ..core import ConfigError
from .main import EXIT_USAGE


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "opcua",
        help="serve the cell's units over OPC UA (OPC 30050 PackML objects)",
        description="An OPC UA server (OPC 30050 'OPC UA for PackML') for the units of a cell "
        "file, configured by its opcua: block: listens on 127.0.0.1:4840 by default, anonymous "
        "sessions are read-only, commands need a configured user or certificate. Ctrl-C stops it.",
    )
    p.add_argument(
        "cell_file", type=Path, nargs="?", help="the cell YAML (e.g. config/demo_cell.yaml)"
    )
    p.add_argument("--host", help="listen address (overrides opcua.host)")
    p.add_argument("--port", type=int, help="TCP port (overrides opcua.port)")
    p.add_argument("--state-dir", type=Path, help="where a generated certificate is kept")
    p.add_argument("--check", action="store_true", help="only validate the configuration")
    p.add_argument(
        "--hash-password",
        action="store_true",
        help="read a password (prompt or stdin) and print the hash to put under opcua.users",
    )
    p.set_defaults(func=opcua)


def opcua(args: argparse.Namespace) -> int:
    from ..opcua.config import hash_password, parse_opcua, with_overrides

    if args.hash_password:
        password = getpass.getpass("password: ") if sys.stdin.isatty() else sys.stdin.readline()
        print(hash_password(password.rstrip("\n")))
        return 0
    if args.cell_file is None:
        print("packml opcua: give a cell file (e.g. config/demo_cell.yaml)", file=sys.stderr)
        return EXIT_USAGE
    from ..core import load_cell

    try:
        cell = load_cell(args.cell_file)
        config = with_overrides(
            parse_opcua(cell), host=args.host, port=args.port, state_dir=args.state_dir
        )
    except ConfigError as exc:
        print(exc.prefixed("packml opcua"), file=sys.stderr)
        return EXIT_USAGE
    if args.check:
        print(
            f"{args.cell_file}: opcua block valid ({config.endpoint}, units: {', '.join(config.units)})"
        )
        return 0
    import asyncio
    import logging

    from .. import run
    from ..opcua.server import quiet_asyncua, serve

    run.cell_environment(cell.discovery, tool=True)
    run.default_environment(tool=True)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    quiet_asyncua()
    try:
        return asyncio.run(serve(cell, config, ready=lambda text: print(text, flush=True)))
    except OSError as exc:
        print(f"packml opcua: cannot listen on {config.endpoint}: {exc.strerror}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        return 0
