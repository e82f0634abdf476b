"""A short-lived ROS session for command-line verbs: rclpy on its own context, one node spun in
a background thread, unit and cell lookup by name, and answers turned into exit codes."""

from __future__ import annotations

import argparse
import os
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import rclpy
from rclpy.context import Context
from rclpy.executors import ExternalShutdownException

from .. import run
from ..boundary import GuardedNode
from ..client import CellProxy, Unavailable, UnitProxy, discover_cells
from ..executors import MultiThreadedExecutor


class Session:
    def __init__(
        self, args: argparse.Namespace, topics: tuple[str, ...] = UnitProxy.topics
    ) -> None:
        self.args = args
        self.topics = topics  # what the units' proxies follow (see UnitProxy.topics)
        self.timeout: float = getattr(args, "timeout", 5.0)
        self.context = Context()
        run.default_environment(tool=True)
        rclpy.init(
            context=self.context, signal_handler_options=rclpy.signals.SignalHandlerOptions.NO
        )
        self.node = GuardedNode(f"packml_cli_{os.getpid()}", context=self.context)
        self.executor = MultiThreadedExecutor(context=self.context)
        self._closing = False
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()
        self._cells: dict[str, CellProxy] = {}
        self._discovered: set[str] = set()
        self._graph: dict[str, list[str]] | None = None

    def _spin(self) -> None:
        try:
            self.executor.spin()
        except (ExternalShutdownException, rclpy.executors.ShutdownException):
            pass
        except RuntimeError as exc:
            # rclpy 9.1: MultiThreadedExecutor.shutdown closes its thread pool while spin() may
            # still hand it a callback (ros2/rclpy#1724); nothing is lost at the end of a verb.
            # Also a callback that ends as the node is destroyed (InvalidHandle: "destruction was
            # requested"), e.g. a proxy's deaf watch firing as a verb gives up and closes.
            closed = "after shutdown" in str(exc) or "destruction was requested" in str(exc)
            if not (self._closing and closed):
                raise

    def close(self) -> None:
        self._closing = True
        self.executor.shutdown(timeout_sec=2)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)
        self._thread.join(2)
        # a callback that ran into the node's destruction leaves its task failed; rclpy prints
        # "The following exception was never retrieved" when such a task is collected: shutdown
        # noise on the user's terminal, not a result of the verb. Fetch it here.
        for task, *_ in list(getattr(self.executor, "_tasks", ())):
            if task.done() and not task.cancelled():
                task.exception()

    # -- finding things ----------------------------------------------------------------------------
    def graph(self) -> dict[str, list[str]]:
        """The cells and units on the graph, discovered once per session."""
        if self._graph is None:
            self._graph = discover_cells(self.node, self.timeout)
        return self._graph

    def cells(self) -> dict[str, list[str]]:
        wanted = getattr(self.args, "cell", None)
        found = self.graph()
        if wanted:
            return {wanted: found.get(wanted, [])}
        return found

    def cell(self, name: str | None = None, discover: bool = True) -> CellProxy:
        """The cell ``name`` (or --cell, or the only cell on the graph); with ``discover``, with
        all its units (see :meth:`CellProxy.discover`)."""
        name = name or getattr(self.args, "cell", None)
        if name is None:
            cells = self.graph()
            if not cells:
                raise Unavailable("no PackML unit found (is a cell running? same ROS_DOMAIN_ID?)")
            if len(cells) > 1:
                raise LookupError(
                    f"several cells are running ({', '.join(cells)}): choose one with --cell"
                )
            name = next(iter(cells))
        if name not in self._cells:
            self._cells[name] = CellProxy(self.node, name, topics=self.topics)
        proxy = self._cells[name]
        if discover and name not in self._discovered:
            proxy.discover(self.timeout)
            self._discovered.add(name)
        return proxy

    def unit(self, name: str) -> UnitProxy:
        """A unit by ``unit``, ``cell/unit`` or ``/cell/unit``."""
        if "/" in name.strip("/"):
            cell, unit = name.strip("/").split("/", 1)
            return self.cell(cell, discover=False).unit(unit)
        cell_name = getattr(self.args, "cell", None)
        if cell_name is None:
            cells = self.graph()
            owners = [c for c, units in cells.items() if name in units]
            if not owners:  # perhaps not discovered yet (the graph stops early with a coordinator)
                cells = self._graph = discover_cells(self.node, self.timeout, until=name)
                owners = [c for c, units in cells.items() if name in units]
            if not owners:
                known = ", ".join(f"{c}/{u}" for c, units in cells.items() for u in units) or "none"
                raise LookupError(f"no unit {name!r} found (units: {known})")
            if len(owners) > 1:
                raise LookupError(
                    f"unit {name!r} exists in cells {', '.join(owners)}: write cell/{name}"
                )
            cell_name = owners[0]
        return self.cell(cell_name, discover=False).unit(name)

    def is_cell(self, name: str) -> bool:
        """Whether ``name`` is a running cell rather than a unit."""
        if "/" in name.strip("/"):
            return False
        cells = self.graph()
        return name in cells and not any(name in units for units in cells.values())


@contextmanager
def session(
    args: argparse.Namespace, topics: tuple[str, ...] = UnitProxy.topics
) -> Iterator[Session]:
    s = Session(args, topics)
    try:
        yield s
    finally:
        s.close()


def add_common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--cell", help="cell namespace (default: the only cell running)")
    parser.add_argument(
        "--timeout",
        type=float,
        default=5.0,
        help="seconds to wait for discovery and answers (default 5)",
    )


def fail(message: str, code: int) -> int:
    print(f"packml: {message}", file=sys.stderr)
    return code


def describe(resp: Any) -> str:
    return getattr(resp, "message", "") or getattr(resp, "message_out", "")
