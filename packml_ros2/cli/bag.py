"""``packml record`` and ``packml replay``: rosbag2 recordings of units as regression tests."""

from __future__ import annotations

import argparse
import signal
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

from .main import EXIT_OK, EXIT_REFUSED, EXIT_UNAVAILABLE, EXIT_USAGE

#: ``packml replay``: the recording differs from the replay (1), the bag cannot be replayed (2).
EXIT_MISMATCH, EXIT_UNUSABLE = EXIT_REFUSED, EXIT_USAGE

#: Why ``packml record`` writes mcap only (issue 27).
SQLITE_WHY = (
    "rosbag2's sqlite3 storage keeps every message uncompressed in a row of its own: 39 MB per "
    "hour of the demo cell's robot_cell against 2 MB for mcap, four times the 10 MB budget; "
    "record mcap and convert the bag with `ros2 bag convert` if a tool needs sqlite3 "
    "(packml replay reads both)"
)

RECORD_EPILOG = """\
targets: cell/unit (or /cell/unit) records one unit without looking at the graph (it may start
later); a unit or cell name is looked up on the graph; a cell records all its units and
/<cell>/coordinator/status. With --config, a cell's units come from the file.

The bag (mcap, zstd-compressed chunks) holds per unit: input_log, em_reports, config, snapshot,
status, transitions, admin, alarms, and per cell its coordinator's status and line topics, with the
publishers' QoS and the type definitions, so rosbag2 and other tools read it. Stop with Ctrl-C (or
--duration): the bag is closed cleanly.

{SQLITE_WHY}

exit codes: 0 recorded, 1 refused, 2 usage, 3 the target was not found on the graph
"""

REPLAY_EPILOG = """\
--check (the default) replays every input of the bag through a fresh engine on the bag's own clock
and compares every recorded status, transition, alarm list and admin message on decoded values;
on a difference it prints the first diverging transition and the inputs that led to it.
--update writes the replayed outputs into the bag (in place, or into -o).
--live sends the recorded inputs to running unit nodes (start them first, without EMs) at the
recorded pace / --speed and compares the transitions (states, modes, triggers) and the final state.

Recorded from any moment: a bag whose input log does not reach back to the unit's start replays
from the snapshot of the unit's state the recorder received when it joined. Outputs are compared
up to the recorder's stop: a message the unit published before it and the bag lacks is a
difference, as is one the bag has and the replay does not produce.

The line of a recorded cell (its coordinator's input log, snapshot, episodes and losses) is
replayed and compared the same way. --junit FILE writes JUnit XML: one test case per unit and per
line check (episodes, losses), so a CI system shows which one failed.

exit codes: 0 match, 1 mismatch, 2 usage error or the bag is not a replayable PackML recording
(no configuration, recorded by a newer version), 3 (--live) a unit is not running or not freshly
started; a malformed recording, each its own: 4 the file is cut short or damaged, 5 input stamps
out of order, 6 an input recorded twice, 7 inputs missing (a gap, or neither the start nor a
snapshot), 8 the unit or coordinator started again during the recording
"""


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "record",
        help="record a unit's or a cell's inputs and outputs into a rosbag2 bag",
        description="Record the inputs (input log, EM reports, configuration) and outputs "
        "(status, transitions, admin, alarms) of units into a rosbag2 bag.",
        epilog=RECORD_EPILOG.format(
            SQLITE_WHY=textwrap.fill(f"sqlite3 is not offered: {SQLITE_WHY}.", 99)
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("targets", nargs="*", metavar="target", help="cell/unit, unit or cell")
    p.add_argument(
        "-o", "--output", help="bag directory to create (default packml_<target>_<time>)"
    )
    p.add_argument("--storage", default="mcap", help="mcap (the only one offered; see below)")
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    p.add_argument("--config", help="cell YAML: the units of a cell target (no graph look-up)")
    p.add_argument("--cell", help="cell namespace for bare unit names")
    p.add_argument("--timeout", type=float, default=5.0, help="seconds to look for targets (5)")
    p.set_defaults(func=record)

    p = subparsers.add_parser(
        "replay",
        help="replay a bag through a fresh unit and compare the outputs (regression test)",
        description="Replay a recorded bag and compare the outputs with the recorded ones.",
        epilog=REPLAY_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("bag", help="bag directory (metadata.yaml), or an .mcap/.db3 file")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--check", action="store_true", help="offline replay-check (default)")
    mode.add_argument("--update", action="store_true", help="rewrite the expected outputs")
    mode.add_argument("--live", action="store_true", help="feed running nodes instead")
    p.add_argument("-o", "--output", help="--update: write a new bag here (default: in place)")
    p.add_argument("--config", help="cell YAML to use instead of the recorded configuration")
    p.add_argument("--unit", action="append", default=[], help="only this unit (repeatable)")
    p.add_argument("--speed", type=float, default=1.0, help="--live: recorded pace x SPEED (1)")
    p.add_argument("--timeout", type=float, default=10.0, help="--live: seconds to find units")
    p.add_argument("--settle", type=float, default=5.0, help="--live: seconds to wait at the end")
    p.add_argument("--junit", metavar="FILE", help="--check: also write the result as JUnit XML")
    p.set_defaults(func=replay)


def _fail(message: str, code: int) -> int:
    print(f"packml: {message}", file=sys.stderr)
    return code


# -- record ----------------------------------------------------------------------------------------
def _targets(args: argparse.Namespace, node: Any) -> tuple[list[str], list[str]]:
    """(unit paths, cells whose coordinator status is recorded)."""
    from ..client import discover_cells
    from ..core import load_cell

    units: list[str] = []
    cells: list[str] = []
    config = load_cell(args.config) if args.config else None
    names = list(args.targets)
    if not names and config is not None:
        names = [config.cell]
    if not names:
        raise ValueError("name a target: cell/unit, a unit or a cell (or give --config)")
    found: dict[str, list[str]] | None = None
    for name in names:
        parts = name.strip("/").split("/")
        if len(parts) == 2:
            units.append("/" + "/".join(parts))
            continue
        if len(parts) != 1 or not parts[0]:
            raise ValueError(f"{name!r} is neither cell/unit, a unit nor a cell")
        if config is not None and name == config.cell:
            units += [f"/{config.cell}/{u}" for u in config.units]
            cells.append(config.cell)
            continue
        if config is not None and name in config.units:
            units.append(f"/{config.cell}/{name}")
            continue
        if args.cell:
            units.append(f"/{args.cell}/{name}")
            continue
        if found is None:
            found = discover_cells(node, args.timeout)
        if name in found:
            units += [f"/{name}/{u}" for u in found[name]]
            cells.append(name)
            continue
        owners = [c for c, us in found.items() if name in us]
        if not owners:
            known = ", ".join(f"{c}/{u}" for c, us in found.items() for u in us) or "none"
            raise LookupError(f"no unit or cell {name!r} found (units: {known})")
        if len(owners) > 1:
            raise LookupError(f"unit {name!r} is in cells {', '.join(owners)}: write cell/{name}")
        units.append(f"/{owners[0]}/{name}")
    return list(dict.fromkeys(units)), list(dict.fromkeys(cells))


def record(args: argparse.Namespace) -> int:
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    from .. import run
    from ..bag.record import Recorder, run_recorder
    from ..core import ConfigError

    if args.duration is not None and args.duration <= 0:
        return _fail("--duration must be > 0", EXIT_USAGE)
    if args.storage != "mcap":
        return _fail(
            f"--storage {args.storage}: packml record writes mcap; {SQLITE_WHY}", EXIT_USAGE
        )
    run.default_environment(tool=True)
    context = Context()
    rclpy.init(context=context, signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
    stop = {"now": False}

    def on_signal(*_: Any) -> None:
        stop["now"] = True

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    executor = SingleThreadedExecutor(context=context)
    probe = Node(f"packml_record_probe_{id(stop) % 100000}", context=context)
    executor.add_node(probe)
    try:
        try:
            units, cells = _targets(args, probe)
        except (ValueError, ConfigError) as exc:
            return _fail(str(exc), EXIT_USAGE)
        except LookupError as exc:
            return _fail(f"{exc} (is the cell running? same ROS_DOMAIN_ID?)", EXIT_UNAVAILABLE)
        if not units:
            return _fail("no unit to record", EXIT_UNAVAILABLE)
        out = Path(args.output or _default_name(units))
        if out.exists():
            return _fail(f"{out} exists already: choose another -o", EXIT_USAGE)
        recorder = Recorder(out, units, cells, storage=args.storage, context=context)
        executor.add_node(recorder.node)
        topics = len(recorder.counts)
        print(
            f"recording {', '.join(units)} ({topics} topics) into {out} ({args.storage}); "
            "Ctrl-C to stop",
            file=sys.stderr,
            flush=True,
        )

        def announce(unit: str) -> None:
            print(f"receiving {unit}", file=sys.stderr, flush=True)

        run_recorder(recorder, executor, lambda: stop["now"], args.duration, announce=announce)
        total = sum(recorder.counts.values())
        counts = ", ".join(f"{t.rsplit('/', 1)[-1]} {n}" for t, n in recorder.counts.items() if n)
        print(f"wrote {out}: {total} messages ({counts or 'none'})", file=sys.stderr)
        for topic, n in recorder.lost().items():
            print(
                f"packml: warning: the recorder missed {n} message(s) on {topic}", file=sys.stderr
            )
        if not any(recorder.received(f"{u}/input_log") for u in units):
            print(
                "packml: warning: no input log received: replay needs one (is the unit "
                "running with record_inputs true?)",
                file=sys.stderr,
            )
        return EXIT_OK
    finally:
        for s, handler in old.items():
            signal.signal(s, handler)
        executor.shutdown(timeout_sec=2)
        probe.destroy_node()
        rclpy.try_shutdown(context=context)


def _default_name(units: list[str]) -> str:
    name = (
        units[0].strip("/").replace("/", "_")
        if len(units) == 1
        else units[0].strip("/").split("/")[0]
    )
    return f"packml_{name}_{time.strftime('%Y%m%d-%H%M%S')}"


# -- replay ----------------------------------------------------------------------------------------
def replay(args: argparse.Namespace) -> int:
    from ..bag.recording import RecordingError

    if not Path(args.bag).exists():
        return _fail(f"{args.bag}: no such bag", EXIT_USAGE)
    if args.config and not Path(args.config).exists():
        return _fail(f"{args.config}: no such file", EXIT_USAGE)
    if args.output and not args.update:
        return _fail("-o goes with --update", EXIT_USAGE)
    if args.junit and (args.update or args.live):
        return _fail("--junit goes with --check", EXIT_USAGE)
    started = time.perf_counter()
    try:
        if args.live:
            return _live(args)
        if args.update:
            from ..bag.replay import update

            result, dst = update(args.bag, args.output, args.config)
            n = sum(sum(u.compared.values()) for u in result.units)
            was = "matched already" if result.ok else f"{len(result.differences)} topic(s) differed"
            print(
                f"updated {dst}: expected outputs rewritten from the replay ({n} compared; {was})"
            )
            return EXIT_OK
        from ..bag import line
        from ..bag.replay import replay as check

        lines = line.check(args.bag, args.config) if not args.unit else []
        checked = (
            None if lines and not _has_units(args.bag) else check(args.bag, args.config, args.unit)
        )
    except RecordingError as exc:
        if args.junit:
            _junit(args, time.perf_counter() - started, None, [], exc)
        return _fail(f"{exc} [{exc.reason}]", exc.exit_code)
    except KeyError as exc:
        return _fail(str(exc.args[0] if exc.args else exc), EXIT_USAGE)
    except (RecursionError, MemoryError) as exc:  # what no check of the bag foresaw: still input
        return _fail(
            f"{args.bag}: cannot replay the bag: {type(exc).__name__} (nested too deeply, or larger than memory)",
            EXIT_UNUSABLE,
        )
    seconds = time.perf_counter() - started  # the whole check: units and line
    if checked is not None:
        checked.seconds = seconds
        print(checked.report())
    for r in lines:
        print(r.report())
    ok = (checked is None or checked.ok) and all(r.ok for r in lines)
    if checked is None:
        print(f"{args.bag}: {'match' if ok else 'MISMATCH'} ({seconds:.2f} s)")
    if args.junit:
        _junit(args, seconds, checked, lines, None)
    return EXIT_OK if ok else EXIT_MISMATCH


def _junit(args: argparse.Namespace, seconds: float, result: Any, lines: Any, error: Any) -> None:
    from ..bag import junit

    junit.write(args.junit, args.bag, seconds, result, lines, error)


def _has_units(bag: str) -> bool:
    """Whether the bag holds more of a unit than its configuration (which the line's replay
    reads too)."""
    from ..bag.recording import load

    units = load(bag, em_reports=False).units.values()
    return any(u.inputs or u.snapshots or any(u.outputs.values()) for u in units)


def _live(args: argparse.Namespace) -> int:
    from ..bag.live import Unavailable, replay_live

    if args.speed <= 0:
        return _fail("--speed must be > 0", EXIT_USAGE)
    try:
        result = replay_live(args.bag, args.speed, args.unit, args.timeout, args.settle)
    except Unavailable as exc:
        return _fail(str(exc), EXIT_UNAVAILABLE)
    print(result.report())
    return EXIT_OK if result.ok else EXIT_MISMATCH
