"""Running nodes from entry points: localhost-only defaults, an executor, and a clean exit on
Ctrl-C / SIGTERM (exit code 0, no traceback)."""

from __future__ import annotations

import contextlib
import faulthandler
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence

import rclpy
from rclpy.executors import (
    Executor,
    ExternalShutdownException,
    ShutdownException,
    SingleThreadedExecutor,
)
from rclpy.node import Node

from .core import discovery
from .core.discovery import DiscoveryConfig
from .core.safe_yaml import read_document
from .executors import MultiThreadedExecutor
from .paths import fastdds_profile

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class _Shutdown:
    """Process-wide, like signals: whether and why this process's nodes are shutting down."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self.reason = ""

    def request(self, reason: str) -> None:
        if not self.event.is_set():
            self.reason = reason
            self.event.set()

    def reset(self) -> None:
        self.event.clear()
        self.reason = ""


_shutdown = _Shutdown()


def shutting_down() -> bool:
    """Whether this process has been asked to stop (Ctrl-C, SIGTERM) and its nodes are ending:
    inputs that only mean "the rest of the cell is stopping too" (an EM saying goodbye) need no
    reaction any more."""
    return _shutdown.event.is_set()


def shutdown_reason() -> str:
    """What ended :func:`spin`: ``SIGINT``, ``SIGTERM``, ``context shut down``; '' while running."""
    return _shutdown.reason


def default_environment(tool: bool = False) -> None:
    """Keep DDS on this machine unless the user chose otherwise, and discover quickly. ``tool``:
    a process that looks at the whole graph (CLI, HMI, OPC UA face, recorder) is a Discovery
    Server super client when a server is set (core/discovery.py)."""
    discovery_range = os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    profile = fastdds_profile(discovery_range)  # LOCALHOST: transports on loopback only
    if profile.exists():
        os.environ.setdefault("FASTDDS_DEFAULT_PROFILES_FILE", str(profile))
    if tool and os.environ.get("ROS_DISCOVERY_SERVER", "").strip():
        os.environ.setdefault("ROS_SUPER_CLIENT", "TRUE")


def cell_environment(d: DiscoveryConfig, tool: bool = False) -> None:
    """Put this process into the cell's discovery setup (its ``discovery:`` block): before
    rclpy.init. The cell file's choice wins over the environment's."""
    os.environ.update(discovery.environment(d, super_client=tool))


def _cell_file_discovery(args: Sequence[str]) -> None:
    """A node started by hand with its cell file (``unit_node cell.yaml unit``) joins the cell's
    discovery setup; an unreadable file is left to the node's own loading to report."""
    for arg in args[1:]:
        if arg == "--ros-args":
            break
        if arg.endswith((".yaml", ".yml")) and os.path.isfile(arg):
            try:
                found = discovery.from_document(read_document(arg))
            except Exception:  # reported when the node loads the file
                return
            if found is not None:
                cell_environment(found)
            return


def make_executor(nodes: int, threads: int = 0) -> Executor:
    """``threads`` > 1: a multi-threaded executor (one node's long callback does not hold up the
    others). Otherwise rclpy's C++ EventsExecutor, for one node or several whose callbacks never
    block (units, EMs in one process): it halves the latency of a hop compared with the Python
    executors (bench/ros_latency.py measures it), and an idle node costs it nothing, where the
    Python executors rebuild their wait set of every entity at each wake-up (the demo cell in one
    process idled at 27 % of a core on a multi-threaded executor, 7-9 % on one single-threaded,
    3-4 % on this one: bench/scale.py). ``PACKML_EXECUTOR=single`` selects the
    SingleThreadedExecutor."""
    if threads > 1:
        return MultiThreadedExecutor(num_threads=threads)
    if os.environ.get("PACKML_EXECUTOR", "events") == "events":
        from rclpy.experimental.events_executor import EventsExecutor

        return EventsExecutor()
    return SingleThreadedExecutor()


def spin(
    nodes: Sequence[Node],
    threads: int = 0,
    on_shutdown: Callable[[], None] | None = None,
    blocking: Sequence[Node] = (),
    blocking_threads: int = 8,
) -> int:
    """Spin ``nodes`` until Ctrl-C or SIGTERM, then shut down in order; returns the exit code.
    ``on_shutdown`` runs first, while the nodes can still publish (:func:`shutdown_reason` says
    why); then the executors and the nodes are destroyed. From the stop on the process has
    :data:`TEARDOWN_LIMIT` to end, here and in the interpreter's exit after ``spin`` returns
    (then every thread's stack goes to stderr and the process exits): ``spin`` is the last thing
    a node process does.

    ``threads``: 0 or 1 = one thread (:func:`make_executor`), also for several nodes whose
    callbacks never block; more = a multi-threaded executor with that many
    threads. ``blocking``: nodes whose callbacks wait for other nodes (the coordinator, a PLC
    bridge), spun by a multi-threaded executor of ``blocking_threads`` in a thread of its own."""
    executor = make_executor(len(nodes), threads)
    for node in nodes:
        executor.add_node(node)
    side: Executor | None = None
    if blocking:
        side = MultiThreadedExecutor(num_threads=blocking_threads)
        for node in blocking:
            side.add_node(node)
    # Ctrl-C and SIGTERM only ask the loop to end: the nodes are shut down below, after the
    # callback that was running has finished. (Shutting the context down from the handler would
    # destroy the nodes under that callback: a traceback, and a half-done update saved.) A
    # callback that runs after the signal arrived sees shutting_down() (Python runs the handler
    # before the callback's first line).
    # (a stop asked for since catch_stop_signals, while the nodes were made, ends the spin at once)
    previous = {s: signal.signal(s, _on_stop_signal) for s in STOP_SIGNALS}
    side_thread = None
    if side is not None:
        side_thread = threading.Thread(
            target=_spin_side, args=(side,), name="packml-blocking", daemon=True
        )
        side_thread.start()
    try:
        _spin_loop(executor)
        _shutdown.request("context shut down")
    except KeyboardInterrupt:
        _shutdown.request("SIGINT")
    except ExternalShutdownException:
        _shutdown.request("context shut down")
    finally:
        # A second Ctrl-C (the terminal's and ros2 launch's arrive together) or a SIGTERM while
        # the nodes shut down changes nothing: the handler stays until they are gone.
        try:
            # From here the shutdown may not hang: on_shutdown (its goodbyes are logged, and a
            # log line is also a DDS write to /rosout: a node once hung right after its goodbye,
            # before a guard armed after on_shutdown), the teardown below (executors, DDS) and
            # the interpreter's exit after spin returns. What the nodes keep survives a kill.
            _guard_teardown()
            if on_shutdown is not None:
                on_shutdown()
            for ex in (executor, side) if side is not None else (executor,):
                _drain(ex, timeout=2.0)
                ex.shutdown(timeout_sec=2)
            if side_thread is not None:
                side_thread.join(2)
            for node in [*nodes, *blocking]:
                node.destroy_node()
            rclpy.try_shutdown()
        finally:
            for s, handler in previous.items():
                if handler is not None:  # None: installed outside Python, cannot be put back
                    signal.signal(s, handler)
    return 0


#: s: from the stop, ``on_shutdown``, the executors, DDS and the interpreter's exit get this
#: long; then the process writes every thread's stack to stderr and exits anyway, code 0 (a teardown stuck in the middleware once in a few runs: ros2 launch
#: would SIGKILL it, packml launch report it)
TEARDOWN_LIMIT = 6.0
#: s: the last resort, TEARDOWN_LIMIT + this: a C thread of faulthandler that needs no GIL (a
#: teardown stuck inside C++ that holds the GIL stops every Python thread, the timer above and
#: the signal handlers too) writes the stacks and exits with code 1
HELD_GIL_GRACE = 4.0


def _guard_teardown() -> None:
    """Arm both watchdogs; neither is cancelled: they end with the process (the interpreter's
    own exit, after spin returns, joins threads and destroys rclpy's C++ objects: it can hang
    too). ``spin`` is the last thing a node process does."""
    faulthandler.dump_traceback_later(TEARDOWN_LIMIT + HELD_GIL_GRACE, exit=True)
    watchdog = threading.Timer(TEARDOWN_LIMIT, _teardown_overdue)
    watchdog.daemon = True
    watchdog.start()


def _teardown_overdue() -> None:
    print(
        f"the ROS 2 teardown did not end within {TEARDOWN_LIMIT:g} s after the nodes were "
        "closed: exiting; where it was:",
        file=sys.stderr,
        flush=True,
    )
    faulthandler.dump_traceback(sys.stderr, all_threads=True)
    os._exit(0)


#: s: the main loop looks at Ctrl-C / SIGTERM at least this often (Python runs its signal
#: handlers in the main thread, between the executor's waits)
SIGNAL_LATENCY = 0.2
#: s: the blocking nodes' executor waits at most this long without news; it rebuilds its wait
#: set of every entity at each wake-up (what an idle coordinator costs): the main loop wakes it
#: when it ends (Executor.shutdown triggers its guard condition)
SIDE_WAIT = 5.0


def _spin_loop(executor: Executor, timeout: float = SIGNAL_LATENCY) -> None:
    """spin_once in a loop, not spin(): the EventsExecutor's spin() does not return on shutdown
    (see the notes); this loop does, for every executor."""
    while rclpy.ok() and not _shutdown.event.is_set():
        executor.spin_once(timeout_sec=timeout)


def _spin_side(executor: Executor) -> None:
    """The blocking nodes' executor, in its thread, until the main loop ends."""
    # the context or the executor shut down: the main loop takes it from there
    with contextlib.suppress(ExternalShutdownException, ShutdownException):
        _spin_loop(executor, SIDE_WAIT)


def _drain(executor: Executor, timeout: float) -> None:
    """Let the callbacks a MultiThreadedExecutor already handed to its threads finish. rclpy 9.1's
    ``Executor.shutdown`` destroys its guard condition without waiting for them (ros2/rclpy#968),
    and such a callback then fails: "The following exception was never retrieved: cannot use
    Destroyable because destruction was requested" on the terminal at every Ctrl-C."""
    pending = getattr(executor, "_futures", None)  # the tasks handed out (rclpy's own list)
    deadline = time.monotonic() + timeout
    while pending and not all(f.done() for f in list(pending)) and time.monotonic() < deadline:
        time.sleep(0.01)


def init(argv: Sequence[str] | None = None) -> list[str]:
    """rclpy.init with the default environment (and the discovery setup of the cell file among
    the arguments); returns the non-ROS arguments."""
    args = list(sys.argv if argv is None else argv)
    _cell_file_discovery(args)
    default_environment()
    rclpy.init(args=args, signal_handler_options=rclpy.signals.SignalHandlerOptions.ALL)
    catch_stop_signals()
    return rclpy.utilities.remove_ros_args(args)[1:]


def catch_stop_signals() -> None:
    """From now on Ctrl-C and SIGTERM only ask :func:`spin` to end (at once, when it begins): a
    signal while the nodes are still being made (a cell stopped as it starts) ends the process
    like one during the spin, exit code 0 and no traceback, instead of a KeyboardInterrupt."""
    _shutdown.reset()
    for s in STOP_SIGNALS:
        signal.signal(s, _on_stop_signal)


def _on_stop_signal(signum: int, _frame: object) -> None:
    _shutdown.request(signal.Signals(signum).name)
