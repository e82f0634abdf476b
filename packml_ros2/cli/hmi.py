"""``packml hmi <cell.yaml>``: the operator HMI of a running cell, in the browser."""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
from dataclasses import replace
from pathlib import Path

from ..core import CellConfig, ConfigError, load_cell, secrets
from ..core.schema import Node
from ..hmi.settings import HmiSettings, check_token, hmi_settings
from .main import EXIT_OK, EXIT_USAGE

TOKEN_ENV = "PACKML_HMI_TOKEN"


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "hmi",
        help="the operator HMI in a browser",
        description="Serve the operator screens of a cell (overview, state diagram, modes, "
        "commands, alarms, EMs, times, counters, OEE) on http://127.0.0.1:<port>/. Every action "
        "goes to the units' services with source 'hmi:<user>'. Host, port, user logins (with "
        "levels operator, maintenance, engineer) or an access token come from the cell file's "
        f"hmi: block; the options and ${TOKEN_ENV} override it. Ctrl-C stops the server.",
    )
    p.add_argument(
        "cell_file", type=Path, nargs="?", help="the cell YAML (e.g. config/demo_cell.yaml)"
    )
    p.add_argument(
        "--hash-password",
        action="store_true",
        help="read a password (prompt or stdin) and print the hash to put under "
        "hmi.users.<name>.password",
    )
    p.add_argument(
        "--host",
        help="interface to serve on (default: hmi.host, else 127.0.0.1; 0.0.0.0 = every "
        "interface: other machines can reach the page)",
    )
    p.add_argument("--port", type=int, help="TCP port (default: hmi.port, else 8080; 0 = any free)")
    p.add_argument(
        "--token",
        metavar="env:VAR|file:PATH",
        help=f"where the access token required for actions is (default: ${TOKEN_ENV}, else "
        "hmi.token); never the token itself, which every user of this machine could read in the "
        "process list; without a token the page can operate freely",
    )
    p.add_argument("--check", action="store_true", help="only validate the hmi: block and exit")
    p.set_defaults(func=hmi)


def hmi(args: argparse.Namespace) -> int:
    if args.hash_password:
        return _hash_password()
    if args.cell_file is None:
        print("packml hmi: give a cell file (e.g. config/demo_cell.yaml)", file=sys.stderr)
        return EXIT_USAGE
    try:
        cell = load_cell(args.cell_file)
        settings = hmi_settings(cell)
        token = _token_override(args.token)
    except ConfigError as exc:
        print(exc.prefixed("packml hmi"), file=sys.stderr)
        return EXIT_USAGE
    settings = replace(
        settings,
        host=args.host or settings.host,
        port=args.port if args.port is not None else settings.port,
        token=(token or None) if token is not None else settings.token,
    )
    if settings.users and settings.token:
        print(
            f"packml hmi: {args.cell_file} has user logins (hmi.users): an access token "
            f"(--token, ${TOKEN_ENV}) cannot be added to them",
            file=sys.stderr,
        )
        return EXIT_USAGE
    if not 0 <= settings.port <= 65535:
        print(f"packml hmi: port {settings.port} is outside 0..65535", file=sys.stderr)
        return EXIT_USAGE
    if args.check:
        n = len(settings.users)
        access = (
            f", {n} user login{'s' if n > 1 else ''}"
            if n
            else ", an access token"
            if settings.token
            else ""
        )
        print(f"{args.cell_file}: hmi valid ({settings.host}:{settings.port}{access})")
        if settings.exposure:
            print(f"packml hmi: warning: {settings.exposure}", file=sys.stderr)
        return EXIT_OK
    return serve(cell, settings)


def _hash_password() -> int:
    """Read a password (a prompt on a terminal, else one line of stdin) and print its hash."""
    import getpass

    password = getpass.getpass("password: ") if sys.stdin.isatty() else sys.stdin.readline()
    password = password.rstrip("\n")
    if len(password) < 8:
        print("packml hmi: a password needs at least 8 characters", file=sys.stderr)
        return EXIT_USAGE
    print(secrets.hash_password(password))
    return EXIT_OK


def _token_override(option: str | None) -> str | None:
    """The token from ``--token env:VAR|file:PATH``, else ``$PACKML_HMI_TOKEN`` (``""``: none),
    else None (the cell file's)."""
    if option is not None:
        node = Node(option, "--token")
        token = node.parse(lambda n: check_token(secrets.resolve(n, Path.cwd())), "")
        if node.problems:
            raise ConfigError("packml hmi", node.problems)
        return token
    value = os.environ.get(TOKEN_ENV)
    if not value:
        return value
    node = Node(value, f"${TOKEN_ENV}")
    node.parse(lambda n: check_token(n.value), "")
    if node.problems:
        raise ConfigError("environment", node.problems)
    return value


def serve(cell: CellConfig, settings: HmiSettings) -> int:
    from .. import run
    from ..hmi.bridge import Bridge
    from ..hmi.server import Server, bind, url_of

    run.cell_environment(cell.discovery, tool=True)
    run.default_environment(tool=True)
    logging.basicConfig(level=logging.WARNING, format="packml hmi: %(message)s")
    try:
        sock = bind(settings.host, settings.port)
    except OSError as exc:
        print(
            f"packml hmi: cannot serve on {settings.host}:{settings.port}: {exc.strerror or exc}",
            file=sys.stderr,
        )
        return EXIT_USAGE
    bridge = Bridge(
        cell,
        token=settings.token,
        users=settings.users,
        logout_after=settings.logout_after,
        title=settings.title,
    )
    try:
        bridge.spin_in_background()
        server = Server(bridge, sock, allowed_hosts=(*settings.allowed_hosts, settings.host))
        access = (
            f"{len(settings.users)} user login(s): read-only until someone logs in"
            if settings.users
            else "an access token is required for commands (read-only without it)"
            if settings.token
            else "no access token: whoever opens the page can operate"
        )
        print(
            f"PackML HMI for cell {cell.cell}: {url_of(sock, settings.host)}  ({access})",
            flush=True,
        )
        if settings.exposure:
            print(f"packml hmi: warning: {settings.exposure}", file=sys.stderr, flush=True)
        # uvicorn handles Ctrl-C/SIGTERM while it runs and raises the signal again afterwards:
        # let that land here, so the bridge closes and the exit code is 0.
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: None)
        server.run()
    finally:
        bridge.close()
        sock.close()
    return EXIT_OK
