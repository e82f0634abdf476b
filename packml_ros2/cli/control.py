"""``packml cmd``, ``packml mode`` and ``packml fault``: change a unit or a whole cell."""

from __future__ import annotations

import argparse
import threading
import time
from typing import Any

from packml_interfaces.srv import Command, SetMode
from std_srvs.srv import SetBool

from ..client import Unavailable, call_blocking, call_future, command_number
from .main import EXIT_OK, EXIT_REFUSED, EXIT_UNAVAILABLE, EXIT_USAGE
from .session import Session, add_common, fail, session
from .status import wait_cell


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "cmd",
        help="send a state command to a unit or a whole cell",
        description="Send a PackML command (reset, start, stop, hold, unhold, suspend, unsuspend, "
        "abort, clear, complete, or its number 1..10) to a unit, or to a cell through its "
        "coordinator. Waits until the unit settles (the state the command leads to, e.g. Idle "
        "after reset); exit code 1 and the reason when refused or when it settles elsewhere.",
    )
    p.add_argument("target", help="a unit (name, cell/unit) or a cell")
    p.add_argument("command", help="command name or number")
    p.add_argument("--no-wait", action="store_true", help="answer as soon as the unit accepted")
    p.add_argument(
        "--wait-timeout",
        type=float,
        default=60.0,
        help="seconds to wait for the unit to settle (default 60)",
    )
    p.add_argument(
        "--source",
        default="operator",
        help="who asks (default: operator; remote:<who> needs remote commands on)",
    )
    add_common(p)
    p.set_defaults(func=cmd)

    p = subparsers.add_parser(
        "mode",
        help="change the mode of a unit or a whole cell",
        description="Change the unit mode: production, maintenance, manual, a configured user mode, "
        "or its number. Exit code 1 and the reason when refused.",
    )
    p.add_argument("target", help="a unit (name, cell/unit) or a cell")
    p.add_argument("mode", help="mode name or number")
    p.add_argument("--source", default="operator")
    add_common(p)
    p.set_defaults(func=mode)

    p = subparsers.add_parser(
        "fault",
        help="switch a simulated EM fault on or off",
        description="Switch a fault of a simulated EM (the faults: block of its sim configuration).",
    )
    p.add_argument("em", help="unit/em or cell/unit/em, e.g. robot_cell/gripper")
    p.add_argument("fault", help="fault name, e.g. vacuum_loss")
    p.add_argument("state", choices=["on", "off"])
    add_common(p)
    p.set_defaults(func=fault)


def _report(resp: Any, ok_text: str) -> int:
    print(resp.message or ok_text)
    return EXIT_OK if resp.accepted else EXIT_REFUSED


def _coordinator(
    s: Session, cell: str, service: str, srv: Any, request: Any, timeout: float
) -> Any:
    client: Any = s.node.create_client(srv, f"/{cell}/coordinator/{service}")
    if not client.wait_for_service(timeout_sec=s.timeout):
        raise Unavailable(
            f"the coordinator of cell {cell} does not answer (/{cell}/coordinator/{service})"
        )
    return call_blocking(client, request, timeout, f"/{cell}/coordinator/{service}")


def _cell_command(s: Session, cell_name: str, request: Any, timeout: float) -> Any:
    """The cell command through the coordinator; while its sequence runs, one line per unit
    state change as it happens (``  robot_cell: STOPPING (0.05 s)``), flushed at once, on a
    terminal and in a pipe alike: a cell Stop takes seconds per unit."""
    cell = s.cell(cell_name)
    wait_cell(cell, s.timeout)  # the states before (a lost unit is not waited for)
    path = f"/{cell_name}/coordinator/command"
    client: Any = s.node.create_client(Command, path)
    if not client.wait_for_service(timeout_sec=s.timeout):
        raise Unavailable(f"the coordinator of cell {cell_name} does not answer ({path})")
    changed = threading.Event()
    cell.on_change = lambda *_: changed.set()
    for u in cell.units.values():
        u.on_change = cell.on_change
    shown = {
        name: u.status.state_current_name if u.status else "" for name, u in cell.units.items()
    }
    t0 = time.monotonic()
    answer = call_future(client, request, path)
    deadline = t0 + timeout
    while not answer.done() and time.monotonic() < deadline:
        changed.wait(0.25)
        changed.clear()
        for name, u in cell.units.items():
            st = u.status
            if st is not None and st.state_current_name != shown[name]:
                shown[name] = st.state_current_name
                print(
                    f"  {name}: {st.state_current_name} ({time.monotonic() - t0:.2f} s)", flush=True
                )
    try:
        return answer.result(max(0.0, deadline - time.monotonic()))
    except TimeoutError:
        raise Unavailable(f"{path} did not answer within {timeout:g} s") from None


def _settled(unit: Any, resp: Command.Response, before: int, timeout: float) -> int:
    """Wait until the unit, past the sequence it had before the command, is no longer on its way
    (StateChangeInProcess false): statuses of different topics are not ordered with the answer."""
    t0 = time.monotonic()
    status = unit.wait_status(
        lambda st: st.sequence > before and not st.state_change_in_process, timeout
    )
    took = time.monotonic() - t0
    if status.state_current == resp.state_requested:
        print(f"now {status.state_current_name} ({took:.2f} s)")
        return EXIT_OK
    banner = f": {status.alarm_banner}" if status.alarm_banner else ""
    print(f"settled in {status.state_current_name} instead ({took:.2f} s){banner}")
    return EXIT_REFUSED


def cmd(args: argparse.Namespace) -> int:
    try:
        number = command_number(args.command)
    except ValueError as exc:
        return fail(str(exc), EXIT_USAGE)
    with session(args, topics=("status",)) as s:
        try:
            if s.is_cell(args.target):
                req = Command.Request(command=number, source=args.source)
                # a cell sequence waits for every unit: allow a step timeout per unit
                return _report(_cell_command(s, args.target, req, 120.0), "accepted")
            unit = s.unit(args.target)
            before = unit.wait_status(timeout=s.timeout).sequence
            resp = unit.command(number, args.source, timeout=s.timeout)
            if not resp.accepted or args.no_wait or resp.state_current == resp.state_requested:
                return _report(resp, "accepted")
            print(resp.message, flush=True)
            return _settled(unit, resp, before, args.wait_timeout)
        except LookupError as exc:
            return fail(str(exc), EXIT_USAGE)
        except Unavailable as exc:
            return fail(str(exc), EXIT_UNAVAILABLE)


def mode(args: argparse.Namespace) -> int:
    with session(args, topics=("status",)) as s:
        try:
            if s.is_cell(args.target):
                req = SetMode.Request(source=args.source)
                if args.mode.isdigit():
                    req.mode = int(args.mode)
                else:
                    req.mode_name = args.mode
                return _report(
                    _coordinator(s, args.target, "set_mode", SetMode, req, 60.0), "accepted"
                )
            return _report(
                s.unit(args.target).set_mode(args.mode, args.source, timeout=s.timeout), "accepted"
            )
        except LookupError as exc:
            return fail(str(exc), EXIT_USAGE)
        except Unavailable as exc:
            return fail(str(exc), EXIT_UNAVAILABLE)


def fault(args: argparse.Namespace) -> int:
    parts = args.em.strip("/").split("/")
    if len(parts) not in (2, 3):
        return fail(f"{args.em!r}: give unit/em or cell/unit/em", EXIT_USAGE)
    with session(args, topics=("status",)) as s:
        try:
            if len(parts) == 2:
                unit = s.unit(parts[0])
                path = f"{unit.path}/{parts[1]}"
            else:
                path = "/" + "/".join(parts)
            client: Any = s.node.create_client(SetBool, f"{path}/fault/{args.fault}")
            if not client.wait_for_service(timeout_sec=s.timeout):
                return fail(
                    f"no fault {args.fault!r} at {path} (is it a simulated EM with that fault?)",
                    EXIT_UNAVAILABLE,
                )
            resp = client.call(SetBool.Request(data=args.state == "on"), timeout_sec=s.timeout)
            if resp is None:
                return fail(f"{path} did not answer", EXIT_UNAVAILABLE)
            print(f"{path}: {resp.message}")
            return EXIT_OK if resp.success else EXIT_REFUSED
        except LookupError as exc:
            return fail(str(exc), EXIT_USAGE)
        except Unavailable as exc:
            return fail(str(exc), EXIT_UNAVAILABLE)
