"""``packml conform TARGET``: certify a PackML implementation against the standard.

TARGET is a ROS unit (``/cell/unit``, any implementation serving this package's interface) or
an OPC 30050 server (``opc.tcp://host:port``, with the unit's browse path and the PLC unit's
security options). The model it declares (TR88-2022 or 2015, the Hold and Complete masks, its
modes and their disabled states and mode-change states) comes from a cell file (``--config``,
the unit's entry) or from ``--model``, ``--hold-from``, ``--complete-from`` (then the standard
modes with their default disabled states).

It commands the machine: a target in Production is refused without ``--yes``; ``--dry`` shows
the plan and commands nothing. Exit codes: 0 every check of the profile passed (skips are
checks the face has no way to do), 1 a check failed, 2 usage, configuration or refused to start,
3 the target could not be reached or stopped answering.
"""

from __future__ import annotations

import argparse
import datetime as dt
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from .main import EXIT_OK, EXIT_REFUSED, EXIT_UNAVAILABLE, EXIT_USAGE

PROG = "packml conform"


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "conform",
        help="certify a PackML unit or an OPC 30050 PLC against the standard",
        description="Drive a PackML target through every wait state x command of the model it "
        "declares, its modes and the mode-change matrix, and check its answers, states, "
        "PackTags and times against ISA-TR88.00.02. Commands the machine: use --dry first.",
    )
    p.add_argument("target", help="a ROS unit (/cell/unit) or an OPC UA endpoint (opc.tcp://...)")
    model = p.add_argument_group("the model the target declares")
    model.add_argument("--config", type=Path, help="a cell file whose unit entry describes it")
    model.add_argument("--unit", help="the unit of --config (default: the target's name)")
    model.add_argument("--model", choices=("2022", "2015"), help="the transition table")
    model.add_argument("--hold-from", help="states Hold is accepted in, comma-separated")
    model.add_argument("--complete-from", help="states Complete is accepted in, comma-separated")
    model.add_argument("--modes", help="the modes to check, comma-separated (default: all)")
    run = p.add_argument_group("the run")
    run.add_argument(
        "--profile",
        default="core",
        metavar="core|modes|packtags|all",
        help="core: states x commands; modes: the other modes and the mode-change matrix; "
        "packtags: Admin times and counters; all; or several, e.g. core,packtags (default core)",
    )
    run.add_argument("--yes", action="store_true", help="run on a target found in Production")
    run.add_argument("--dry", action="store_true", help="show what would be done, command nothing")
    run.add_argument(
        "--stop-on-first",
        action="store_true",
        help="stop at the first failure and leave the target there",
    )
    run.add_argument(
        "--timeout",
        action="append",
        default=[],
        metavar="SECONDS|STATE=SECONDS",
        help="seconds an acting state may take (default 10), or one state's (repeatable)",
    )
    run.add_argument(
        "--quiet",
        type=float,
        default=0.3,
        help="seconds a refused request is watched for a change (default 0.3)",
    )
    run.add_argument(
        "--connect-timeout",
        type=float,
        default=10.0,
        help="seconds to reach the target (default 10)",
    )
    out = p.add_argument_group("the report")
    out.add_argument(
        "--format",
        choices=("table", "json", "junit"),
        default="table",
        help="what goes to standard output (default table)",
    )
    out.add_argument("--json", type=Path, help="also write the JSON report to this file")
    out.add_argument("--junit", type=Path, help="also write JUnit XML to this file")
    ua_ = p.add_argument_group("an OPC UA target (as a PLC unit's plc: block)")
    ua_.add_argument(
        "--browse-path",
        default="",
        help="the unit object's browse names below Objects, /-separated, e.g. PackMLObjects/Filler",
    )
    ua_.add_argument(
        "--strict-path",
        action="store_true",
        help="fail a transition whose acting states were not all shown (for a server whose "
        "acting states last longer than its sampling interval)",
    )
    ua_.add_argument("--node-id", default="", help="the unit object's node id (instead)")
    ua_.add_argument(
        "--security-policy",
        default="None",
        choices=("None", "Basic256Sha256", "Aes128_Sha256_RsaOaep", "Aes256_Sha256_RsaPss"),
    )
    ua_.add_argument("--security-mode", default="None", choices=("None", "Sign", "SignAndEncrypt"))
    ua_.add_argument("--user", default="", help="user name")
    ua_.add_argument("--password-file", type=Path, help="a file holding the password")
    ua_.add_argument("--certificate", type=Path, help="this client's certificate (DER or PEM)")
    ua_.add_argument("--private-key", type=Path, help="its private key")
    ua_.add_argument("--server-certificate", type=Path, help="the server's certificate, pinned")
    p.set_defaults(func=conform)


class Usage(Exception):
    """A usage or configuration error: the sentence."""


def _states(text: str | None, flag: str) -> list[Any] | None:
    from ..core.numbers import parse_state

    if text is None:
        return None
    try:
        return [parse_state(t) for t in text.split(",") if t.strip()]
    except (KeyError, ValueError) as exc:
        raise Usage(f"{flag}: {exc}") from None


def declared(args: argparse.Namespace, unit_name: str) -> Any:
    """The unit configuration that declares the target's model."""

    from ..core import ConfigError, load_cell
    from ..core.config import unit_config
    from ..core.rules import build_table

    if args.config is not None:
        try:
            cell = load_cell(args.config)
        except ConfigError as exc:
            raise Usage(exc.prefixed(PROG)) from None
        name = args.unit or unit_name
        if name not in cell.units:
            if args.unit is None and len(cell.units) == 1:
                name = next(iter(cell.units))
            else:
                known = ", ".join(cell.units)
                raise Usage(
                    f"{args.config}: no unit {name!r} (units: {known}); name it with --unit"
                )
        config = cell.units[name]
        if args.model or args.hold_from or args.complete_from:
            raise Usage(
                "--model, --hold-from and --complete-from come from --config: give one or the other"
            )
        return config, cell
    table = build_table(
        args.model or "2022",
        _states(args.hold_from, "--hold-from"),
        _states(args.complete_from, "--complete-from"),
    )
    return replace(unit_config(unit_name or "unit"), table=table), None


def _timeouts(values: list[str]) -> tuple[float, dict[Any, float]]:
    from ..core.numbers import parse_state

    default, per_state = 10.0, {}
    for v in values:
        key, _, seconds = v.rpartition("=")
        try:
            number = float(seconds)
        except ValueError:
            raise Usage(f"--timeout {v}: expected SECONDS or STATE=SECONDS") from None
        if not 0 < number <= 3600:
            raise Usage(f"--timeout {v}: expected 0 < seconds <= 3600")
        if not key:
            default = number
            continue
        try:
            per_state[parse_state(key)] = number
        except (KeyError, ValueError) as exc:
            raise Usage(f"--timeout {v}: {exc}") from None
    return default, per_state


def _modes(text: str | None, config: Any) -> list[int]:
    from ..core.numbers import Mode

    configured = dict(config.modes)
    if text is None:
        first = Mode.PRODUCTION if Mode.PRODUCTION in configured else config.initial_mode
        return [first, *sorted(m for m in configured if m != first)]
    out: list[int] = []
    for item in (t.strip() for t in text.split(",") if t.strip()):
        found = [
            n for n, m in configured.items() if str(n) == item or m.name.lower() == item.lower()
        ]
        if not found:
            names = ", ".join(f"{m.name.lower()} ({n})" for n, m in sorted(configured.items()))
            raise Usage(f"--modes: {item!r} is not a mode of the target (modes: {names})")
        out.append(found[0])
    return list(dict.fromkeys(out))


def _target(args: argparse.Namespace, config: Any, cell: Any) -> Any:
    from ..conform.opcua_target import OpcuaTarget
    from ..conform.ros_target import RosTarget

    if args.target.startswith("opc.tcp://"):
        return OpcuaTarget(_plc(args, config, cell), config, args.strict_path)
    if "/" not in args.target.strip("/"):
        raise Usage(f"{args.target!r}: write the unit as /cell/unit, or an opc.tcp:// endpoint")
    return RosTarget(args.target)


def _plc(args: argparse.Namespace, config: Any, cell: Any) -> Any:

    from ..core import ConfigError
    from ..plc.config import PlcConfig, parse_plc

    if cell is not None and config.plc:
        try:
            plc = parse_plc(cell, config.name)
        except ConfigError as exc:
            raise Usage(exc.prefixed(PROG)) from None
        return replace(plc, endpoint=args.target)
    password = ""
    if args.password_file is not None:
        try:
            password = args.password_file.read_text().strip()
        except OSError as exc:
            raise Usage(f"--password-file: {exc.strerror or exc}") from None
    if (args.security_policy == "None") != (args.security_mode == "None"):
        raise Usage("--security-policy and --security-mode: both None, or neither")
    path = tuple(p for p in args.browse_path.split("/") if p)
    if not path and not args.node_id:
        raise Usage(
            "an OPC UA target needs its unit object: "
            "--browse-path PackMLObjects/<unit> or --node-id"
        )
    return PlcConfig(
        cell="conform",
        unit=config.name,
        endpoint=args.target,
        browse_path=path,
        node_id=args.node_id,
        security_policy=args.security_policy,
        security_mode=args.security_mode,
        user=args.user,
        password=password,
        certificate=args.certificate,
        private_key=args.private_key,
        server_certificate=args.server_certificate,
    )


def conform(args: argparse.Namespace) -> int:
    try:
        return _conform(args)
    except Usage as exc:
        text = str(exc)
        print(text if text.startswith(PROG) else f"{PROG}: {text}", file=sys.stderr)
        return EXIT_USAGE


def _conform(args: argparse.Namespace) -> int:
    from ..conform import report
    from ..conform.plan import describe, order, plan
    from ..conform.runner import Options, Runner
    from ..conform.target import Unreachable
    from ..core.rules import rules_of

    unit_name = (
        args.target.rstrip("/").rsplit("/", 1)[-1]
        if not args.target.startswith("opc.tcp://")
        else ""
    )
    config, cell = declared(args, unit_name)
    rules = rules_of(config)
    modes = _modes(args.modes, config)
    timeout, per_state = _timeouts(args.timeout)
    per_state = {**dict(config.timeouts), **per_state}
    if not 0 < args.quiet <= 10:
        raise Usage("--quiet: expected 0 < seconds <= 10")
    names = {n: m.name for n, m in config.modes.items()}
    try:
        cases = plan(rules, args.profile, modes)
    except ValueError as exc:
        raise Usage(f"--profile: {exc}") from None
    target = _target(args, config, cell)
    from .. import run as run_env

    run_env.default_environment(tool=True)
    try:
        target.connect(args.connect_timeout)
    except Unreachable as exc:
        target.close()
        print(f"{PROG}: {exc}", file=sys.stderr)
        return EXIT_UNAVAILABLE
    try:
        found = target.shown().last
        cases = order(
            rules, cases, *((found.mode, found.state) if found is not None else (None, None))
        )
        where = (
            "unknown"
            if found is None
            else f"{found.state.name} ({names.get(found.mode, found.mode)})"
        )
        if args.dry:
            print(
                f"{PROG} {target.where}: found in {where}; "
                f"profile {args.profile}, {len(cases)} checks"
            )
            for case in cases:
                print(f"  {case.group:<8} {case.name(names)}: {describe(case, rules, names)}")
            print(f"then bring the target back to {where}")
            return EXIT_OK
        if found is not None and found.mode == 1 and not args.yes:
            print(
                f"{PROG}: {target.where} is in PRODUCTION mode ({where}). The run commands the "
                "machine through every state, Start included: run it with --yes once the machine "
                "is safe to move, or --dry to see what it would do.",
                file=sys.stderr,
            )
            return EXIT_USAGE
        options = Options(
            timeout=timeout, timeouts=per_state, quiet=args.quiet, stop_on_first=args.stop_on_first
        )
        about = report.About(
            target.where,
            target.face,
            args.profile,
            _model_text(config),
            names,
            dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
            0.0,
        )
        t0 = time.monotonic()
        width = max((len(c.name(names)) for c in cases), default=10)
        table = args.format == "table"
        if table:
            print(report.header(about, found), flush=True)

        def progress(r: Any) -> None:
            if table:
                print(report.line(r, names, width), flush=True)

        runner = Runner(target, rules, options, names, progress=progress)
        try:
            result = runner.execute(cases)
        except Unreachable as exc:
            result = runner.run
            result.stopped_early = result.lost = True
            result.note = f"the target stopped answering: {exc}"
        about = replace(about, seconds=time.monotonic() - t0)
        if args.json is not None:
            args.json.write_text(report.as_json(result, about, rules) + "\n")
        if args.junit is not None:
            args.junit.write_text(report.junit(result, about, rules))
        if args.format == "json":
            print(report.as_json(result, about, rules))
        elif args.format == "junit":
            print(report.junit(result, about, rules), end="")
        else:
            print(report.footer(result, about))
        if result.lost:
            return EXIT_UNAVAILABLE
        return EXIT_OK if result.passed else EXIT_REFUSED
    finally:
        target.close()


def _model_text(config: Any) -> str:
    from ..core.numbers import Cmd

    table = config.table
    hold = ",".join(sorted(s.name for (s, c), _ in table.commands.items() if c == Cmd.HOLD))
    complete = ",".join(sorted(s.name for (s, c), _ in table.commands.items() if c == Cmd.COMPLETE))
    return f"{table.model} (Hold from {hold}; Complete from {complete})"
