"""Running nodes from entry points: localhost-only defaults, an executor, and a clean exit on
Ctrl-C / SIGTERM (exit code 0, no traceback)."""

from __future__ import annotations

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
    MultiThreadedExecutor,
    SingleThreadedExecutor,
)
from rclpy.node import Node

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


def default_environment() -> None:
    """Keep DDS on this machine unless the user chose otherwise, and discover quickly."""
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    profile = fastdds_profile()
    if profile.exists():
        os.environ.setdefault("FASTDDS_DEFAULT_PROFILES_FILE", str(profile))


def make_executor(nodes: int, threads: int = 0) -> Executor:
    """Several nodes, or ``threads`` > 1: a multi-threaded executor (one node's long callback
    does not hold up the others). One node: rclpy's C++ EventsExecutor, which halves the latency
    of a hop compared with the Python executors (bench/ros_latency.py measures it);
    ``PACKML_EXECUTOR=single`` selects the SingleThreadedExecutor instead."""
    if threads > 1 or (threads == 0 and nodes > 1):
        return MultiThreadedExecutor(num_threads=threads or None)
    if os.environ.get("PACKML_EXECUTOR", "events") == "events":
        from rclpy.experimental import EventsExecutor

        return EventsExecutor()
    return SingleThreadedExecutor()


def spin(
    nodes: Sequence[Node], threads: int = 0, on_shutdown: Callable[[], None] | None = None
) -> int:
    """Spin ``nodes`` until Ctrl-C or SIGTERM, then shut down in order; returns the exit code.
    ``on_shutdown`` runs first, while the nodes can still publish (:func:`shutdown_reason` says
    why); then the executor and the nodes are destroyed.

    ``threads``: 0 = one thread for a single node, a multi-threaded executor (one thread per
    core) for several; 1 = single-threaded; more = a multi-threaded executor with that many
    threads, also for a single node (e.g. one whose service handlers wait for other nodes)."""
    executor = make_executor(len(nodes), threads)
    for node in nodes:
        executor.add_node(node)
    # Ctrl-C and SIGTERM only ask the loop to end: the nodes are shut down below, after the
    # callback that was running has finished. (Shutting the context down from the handler would
    # destroy the nodes under that callback: a traceback, and a half-done update saved.) A
    # callback that runs after the signal arrived sees shutting_down() (Python runs the handler
    # before the callback's first line).
    _shutdown.reset()
    previous = {
        s: signal.signal(s, lambda signum, _: _shutdown.request(signal.Signals(signum).name))
        for s in STOP_SIGNALS
    }
    try:
        # spin_once in a loop, not spin(): the EventsExecutor's spin() does not return on
        # shutdown (see the notes); this loop does, for every executor.
        while rclpy.ok() and not _shutdown.event.is_set():
            executor.spin_once(timeout_sec=0.2)
        _shutdown.request("context shut down")
    except KeyboardInterrupt:
        _shutdown.request("SIGINT")
    except ExternalShutdownException:
        _shutdown.request("context shut down")
    finally:
        # A second Ctrl-C (the terminal's and ros2 launch's arrive together) or a SIGTERM while
        # the nodes shut down changes nothing: the handler stays until they are gone.
        try:
            if on_shutdown is not None:
                on_shutdown()
            _drain(executor, timeout=2.0)
            executor.shutdown(timeout_sec=2)
            for node in nodes:
                node.destroy_node()
            rclpy.try_shutdown()
        finally:
            for s, handler in previous.items():
                if handler is not None:  # None: installed outside Python, cannot be put back
                    signal.signal(s, handler)
    return 0


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
    """rclpy.init with the default environment; returns the non-ROS arguments."""
    default_environment()
    args = list(sys.argv if argv is None else argv)
    rclpy.init(args=args, signal_handler_options=rclpy.signals.SignalHandlerOptions.ALL)
    return rclpy.utilities.remove_ros_args(args)[1:]
