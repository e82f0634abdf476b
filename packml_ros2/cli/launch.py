"""``packml launch <cell.yaml>``: start a whole cell."""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

from ..children import spawn
from ..core import ConfigError, StoreError
from .main import EXIT_USAGE


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "launch",
        help="start a cell: units, EMs (simulated, run or external), coordinator",
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
        help="one-process mode: one multi-threaded executor of this many threads for every node "
        "(default: one thread for the units and EMs, a pool for the coordinator)",
    )
    p.add_argument(
        "--logs", type=Path, help="with --processes: write each node's output to this directory"
    )
    p.add_argument(
        "--check",
        action="store_true",
        help="only validate the cell file, list how every EM will run, and exit",
    )
    p.add_argument(
        "--sim",
        action="store_true",
        help="simulate every EM (a dry run of a real cell file: run: and external: EMs too, "
        "each with its sim: block if it has one)",
    )
    p.add_argument(
        "--hmi",
        nargs="?",
        type=int,
        const=-1,
        metavar="PORT",
        help="also serve the operator HMI (packml hmi) on 127.0.0.1, on PORT or the cell file's "
        "hmi.port (default 8080)",
    )
    p.add_argument(
        "--opcua",
        nargs="?",
        type=int,
        const=-1,
        metavar="PORT",
        help="also serve the units over OPC UA (packml opcua), on PORT or the cell file's "
        "opcua.port (default 4840)",
    )
    p.add_argument(
        "--mqtt",
        action="store_true",
        help="also publish the units to the MQTT broker of the cell file's mqtt: block (packml "
        "mqtt: a Sparkplug B edge node)",
    )
    p.set_defaults(func=launch)


def launch(args: argparse.Namespace) -> int:
    from .. import launcher

    hmi = getattr(args, "hmi", None)
    opcua = getattr(args, "opcua", None)
    mqtt = getattr(args, "mqtt", False)
    exposure = None
    try:
        plan = launcher.plan(args.cell_file, simulate=getattr(args, "sim", False))
        if hmi is not None:  # the optional faces' blocks are checked before anything starts
            from ..hmi import hmi_settings
            from .hmi import TOKEN_ENV

            # (the HMI takes a token from the environment too: then it is not open)
            exposure = None if os.environ.get(TOKEN_ENV) else hmi_settings(plan.cell).exposure
        if opcua is not None:
            from ..opcua import parse_opcua

            parse_opcua(plan.cell)
        if mqtt:
            from ..mqtt import parse_mqtt

            parse_mqtt(plan.cell)
    except ConfigError as exc:
        print(exc.prefixed("packml launch"), file=sys.stderr)
        return EXIT_USAGE
    if args.check:
        print(f"{args.cell_file}: valid ({plan.node_count} nodes)")
        if hmi is not None and exposure:
            print(f"packml launch: warning: the HMI: {exposure}", file=sys.stderr)
        if plan.ems:
            print("Equipment modules:")
            print(launcher.how_ems_run(plan))
        return 0
    from .. import run
    from ..discovery_server import DiscoveryServerError, HostedServer

    run.cell_environment(plan.cell.discovery)  # the cell's domain and server, for every child
    found = plan.cell.discovery
    try:
        hosted = HostedServer(*found.servers[0]) if found.host_server else None
    except DiscoveryServerError as exc:
        print(f"packml launch: {exc}", file=sys.stderr)
        return EXIT_USAGE
    if hosted is not None:
        print(
            f"Discovery server on {hosted.address} (ROS_DISCOVERY_SERVER={found.server_text})",
            flush=True,
        )
    server = _start_server("hmi", args.cell_file, hmi) if hmi is not None else None
    opcua_server = _start_server("opcua", args.cell_file, opcua) if opcua is not None else None
    edge_node = _start_server("mqtt", args.cell_file, -1) if mqtt else None
    try:
        if args.processes:
            if args.logs:
                args.logs.mkdir(parents=True, exist_ok=True)
            return launcher.launch_processes(plan, ready=_ready, log_dir=args.logs)
        return launcher.launch_in_process(plan, threads=args.threads, ready=_ready)
    except StoreError as exc:
        print(f"packml launch: {exc}", file=sys.stderr)
        return EXIT_USAGE
    finally:
        if server is not None:
            launcher._stop_children([("hmi", server)])
        if opcua_server is not None:
            launcher._stop_children([("opcua", opcua_server)])
        if edge_node is not None:
            launcher._stop_children([("mqtt", edge_node)])
        if hosted is not None:  # last: the nodes said goodbye through it
            hosted.stop()


def _start_server(verb: str, cell_file: Path, port: int) -> subprocess.Popen[bytes]:
    """``packml hmi``, ``packml opcua`` or ``packml mqtt`` as a child process (own session: Ctrl-C reaches the
    launcher, which stops it last); it prints its address itself. ``port`` < 0: its default."""
    argv = [sys.executable, "-m", "packml_ros2.cli.main", verb, str(cell_file)]
    if port >= 0:
        argv += ["--port", str(port)]
    return spawn(argv)


def _ready(text: str) -> None:
    print(text, flush=True)
