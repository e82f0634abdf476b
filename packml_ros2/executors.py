"""A multi-threaded executor that hands each callback to a thread before it looks for the next.

rclpy 9.1's :class:`rclpy.executors.MultiThreadedExecutor` submits a ready callback to its thread
pool and returns to its wait loop at once. Until a pool thread has *started* that callback, the
loop yields the same task again (it is neither executing nor done), submits it once more and
waits on a wait set that its own guard condition keeps waking: the spinning thread runs hot and
holds the GIL, and the pool threads that would run the callback hardly get it. Measured here
(``test/test_executors.py``; a unit's status while the test's service call was answered): a
subscription's message, received by DDS within a millisecond, reached its callback 0.1 ms to
3 s later (p50 about 200 ms); with this executor 0.1 to 0.3 ms. The CLI, the coordinator's
blocking services, live replay and the tests' harness all spin with it.

The one change: after submitting a callback, the spinning thread waits (at most
:data:`HAND_OFF`) until a pool thread has taken it. Callbacks still run in parallel, and a pool
whose threads are all busy delays the next hand-off by at most that long, as before.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable
from typing import Any

from rclpy.executors import (
    ConditionReachedException,
    Executor,
    ExternalShutdownException,
    ShutdownException,
    TimeoutException,
)
from rclpy.executors import MultiThreadedExecutor as _RclpyMultiThreaded
from rclpy.node import Node

HAND_OFF = 1.0  #: seconds the spinning thread waits for a pool thread to take a callback


class MultiThreadedExecutor(_RclpyMultiThreaded):
    """rclpy's multi-threaded executor, waiting for each hand-off (see the module)."""

    def _spin_once_impl(
        self,
        timeout_sec: Any = None,
        wait_condition: Callable[[], bool] = lambda: False,
    ) -> None:
        try:
            handler, _entity, _node = self.wait_for_ready_callbacks(
                timeout_sec, None, wait_condition
            )
        except (
            ExternalShutdownException,
            ShutdownException,
            TimeoutException,
            ConditionReachedException,
        ):
            return
        taken = threading.Event()

        def run() -> None:
            taken.set()
            handler()

        self._executor.submit(run)
        self._futures.append(handler)
        taken.wait(HAND_OFF)
        for future in self._futures[:]:
            if future.done():
                self._futures.remove(future)
                future.result()  # raises what the callback raised, as rclpy's does


def spin_in_thread(executor: Executor, *nodes: Node) -> threading.Thread:
    """Add ``nodes`` and spin ``executor`` in a daemon thread until it or its context is shut
    down (the end is not an error)."""
    for node in nodes:
        executor.add_node(node)

    def spin() -> None:
        with contextlib.suppress(ExternalShutdownException, ShutdownException):
            executor.spin()

    thread = threading.Thread(target=spin, name="packml-spin", daemon=True)
    thread.start()
    return thread
