"""Whether a unit is there: one answer for every face (OPC UA server, HMI, CLI, coordinator).

A unit publishes ``<unit>/status`` with DDS liveliness AUTOMATIC and a lease of ``unit_lease``
seconds (``coordinator.unit_lease`` of the cell file, default 3 s; :func:`packml_ros2.qos.
status_publisher`). While the unit's process lives, DDS asserts that liveliness by itself; when the
process dies or the network between us is cut, DDS reports the loss within the lease, with no
message and no polling. :class:`Presence` subscribes to each unit's status asking for the same
lease (Fast DDS measures the silence with the reader's lease) and follows those liveliness
events:

- ``None``: not seen yet, less than one lease after the start (a caller may wait a little),
- ``True``: present (at least one live status writer),
- ``False``: lost (liveliness lost, the writer left, or never seen within one lease of the start).

The live writers are counted from the lowest ``alive_count`` seen, not from 0: Fast DDS (3.2)
takes a writer that leaves while the reader is still matching it off ``alive_count`` although it
never counted it alive; the count goes to -1 and stays one short for good (the next writer that
asserts its liveliness is reported with ``alive_count`` 0, ``alive_count_change`` +1): taken as
it is, a unit that is back would look lost until it goes again. The level only goes down, to a
count reported below it: one at which no writer can be alive.

The subscription is raw (no message is decoded here): consumers keep their own status
subscriptions with the default QoS, which stays compatible with the unit's writer. A unit that
offers a longer lease than ours does not match (DDS: requested < offered) and would look lost:
that is logged once as a configuration mismatch.

The coordinator's ``status`` (CellStatus) carries the same liveliness: follow it with
``message_type=CellStatus`` and the path ``/cell/coordinator``.

``on_change(path, seen)`` is called from the executor thread that spins ``node``; hand it over
to your own loop (``loop.call_soon_threadsafe``).
"""

from __future__ import annotations

import inspect
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

from packml_interfaces.msg import Status
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.subscription import MessageInfo

from . import qos


@dataclass(frozen=True)
class Seen:
    """A unit's presence: ``present`` (None = not known yet), since when (``time.time()``), why."""

    present: bool | None
    since: float
    reason: str = ""

    def describe(self, path: str) -> str:
        """One line for people, e.g. ``/cell/filler is not reachable since 10:42:07 (...)``."""
        if self.present:
            return f"{path} is present"
        if self.present is None:
            return f"{path} has not been seen yet"
        clock = time.strftime("%H:%M:%S", time.localtime(self.since))
        return f"{path} is not reachable since {clock} ({self.reason})"


class Presence:
    """The presence of the units ``paths`` (``/cell/unit``) seen from ``node`` (``message_type``:
    what their ``status`` topic carries)."""

    def __init__(
        self,
        node: Node,
        paths: Iterable[str],
        lease: float,
        on_change: Callable[[str, Seen], None] | None = None,
        callback_group: Any = None,
        message_type: Any = Status,
    ) -> None:
        self.node = node
        self.lease = lease
        self.on_change = on_change
        self._lock = threading.Condition()
        started = time.time()
        self._seen: dict[str, Seen] = {}
        self._warned: set[str] = set()
        self._subs = []
        #: per unit, the alive_count that means no live writer (0, less after a miscount)
        self._none: dict[str, int] = {}
        profile = qos.with_lease(qos.STATUS, lease)
        for path in paths:
            self._seen[path], self._none[path] = Seen(None, started), 0
            events = SubscriptionEventCallbacks(
                liveliness=lambda e, p=path: self._on_liveliness(p, e.alive_count),  # type: ignore[misc]
                incompatible_qos=lambda e, p=path: self._on_incompatible(p),  # type: ignore[misc]
            )
            self._subs.append(
                node.create_subscription(
                    message_type,
                    f"{path}/status",
                    _ignore,
                    profile,
                    raw=True,
                    event_callbacks=events,
                    callback_group=callback_group,
                )
            )
        self._timer = node.create_timer(lease, self._on_start_lease, callback_group=callback_group)

    # -- queries (any thread) ----------------------------------------------------------------------
    def seen(self, path: str) -> Seen:
        with self._lock:
            return self._seen[path]

    def wait_known(self, path: str, timeout: float) -> Seen:
        """Block (not in ``node``'s executor thread) until the presence of ``path`` is known or
        ``timeout`` has passed; the presence then."""
        deadline = time.monotonic() + timeout
        with self._lock:
            while self._seen[path].present is None:
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._lock.wait(left)
            return self._seen[path]

    # -- events (executor thread) ------------------------------------------------------------------
    def _set(self, path: str, present: bool, reason: str, only_unknown: bool = False) -> None:
        with self._lock:
            before = self._seen[path].present
            if before is present or (only_unknown and before is not None):
                return
            seen = self._seen[path] = Seen(present, time.time(), reason)
            self._lock.notify_all()
        if self.on_change is not None:
            self.on_change(path, seen)

    def _on_liveliness(self, path: str, alive_count: int) -> None:
        none = self._none[path] = min(self._none[path], alive_count)  # (module docstring)
        if alive_count > none:
            self._set(path, True, "")
        else:
            self._set(path, False, f"no sign of life for {self.lease:g} s (unit_lease)")

    def _on_incompatible(self, path: str) -> None:
        if path not in self._warned:
            self._warned.add(path)
            self.node.get_logger().warning(
                f"{path}/status offers a liveliness lease longer than this cell's unit_lease "
                f"{self.lease:g} s (coordinator.unit_lease): its presence cannot be followed; "
                "start the unit and this program with the same cell file"
            )

    def _on_start_lease(self) -> None:
        self._timer.cancel()
        for path in list(self._seen):
            self._set(path, False, f"not seen within {self.lease:g} s (unit_lease)", True)

    def destroy(self) -> None:
        self.node.destroy_timer(self._timer)
        for sub in self._subs:
            self.node.destroy_subscription(sub)


def _ignore(msg: Any) -> None:
    """Status messages are the consumers' business; presence needs only the liveliness events."""


def with_info(callback: Callable[[Any, MessageInfo], None]) -> Callable[..., None]:
    """``callback(msg, info)`` as a subscription callback every executor calls right: rclpy's
    Python executors pass (msg, info), its EventsExecutor (rclpy 9.1) one (msg, info) tuple."""

    def call(*args: Any) -> None:
        msg, info = args if len(args) == 2 else args[0]
        callback(msg, info)

    two = inspect.Parameter.POSITIONAL_ONLY
    call.__signature__ = inspect.Signature(  # type: ignore[attr-defined]  # what rclpy inspects
        [inspect.Parameter("msg", two), inspect.Parameter("info", two)]
    )
    return call
