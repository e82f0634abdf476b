"""Service responses that survive a client discovered late.

With Fast DDS a service can only answer a client whose *response reader* it has discovered. When a
request arrives first (a client created a moment ago, a busy machine), rmw_fastrtps waits 100 ms for
that reader, then drops the response: rclpy only prints ``RuntimeWarning: failed to send response
(timeout)``. The request was executed, but the caller never hears back: ``packml cmd`` reports
"did not answer" for a command that was carried out.

:func:`create_service` creates a service whose lost responses are sent again from a background
thread (every 50 ms; each attempt may wait up to 100 ms inside the middleware) until one is
delivered, the client has gone away, or ``PACKML_RESPONSE_RESEND_S`` seconds (default 10) have
passed; each loss and its outcome is logged by the node. Lost responses are recognised by that
warning, seen through a ``warnings.showwarning`` hook that chains to the previous one. Inside
``warnings.catch_warnings(record=True)`` (pytest wraps each test in one) that hook is bypassed and
nothing is re-sent; node processes are not affected.
"""

from __future__ import annotations

import functools
import heapq
import itertools
import os
import re
import threading
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from rclpy.node import Node

from . import boundary, qos
from .core.numbers import Cmd

LOST_MESSAGE = "failed to send response (timeout)"
RESEND_PERIOD_S = 0.05
_RESEND_ENV = "PACKML_RESPONSE_RESEND_S"

_watch = threading.local()  # .active: a send of ours is in progress; .lost: it was dropped


def resend_window() -> float:
    """Seconds during which a lost response is sent again (``PACKML_RESPONSE_RESEND_S``)."""
    raw = os.environ.get(_RESEND_ENV, "10")
    try:
        value = float(raw)
    except ValueError:
        raise ValueError(f"{_RESEND_ENV}={raw!r}: expected a number of seconds") from None
    if value < 0:
        raise ValueError(f"{_RESEND_ENV}={raw!r}: must be 0 or more seconds")
    return value


def _install_hook() -> None:
    """Show every lost-response warning (not once per location) and, while one of our sends is in
    progress on this thread, record it instead of printing it. Called once, by :func:`resender`."""
    warnings.filterwarnings("always", message=re.escape(LOST_MESSAGE), category=RuntimeWarning)
    previous = warnings.showwarning

    def showwarning(message: Any, category: Any, *args: Any, **kwargs: Any) -> None:
        if getattr(_watch, "active", False) and str(message).startswith(LOST_MESSAGE):
            _watch.lost = True
            return
        previous(message, category, *args, **kwargs)

    warnings.showwarning = showwarning


def send_watched(send: Callable[[Any, Any], None], response: Any, header: Any) -> bool:
    """``send(response, header)``; True if it was delivered (or its client is gone), False if the
    middleware dropped it because the client's response reader is not discovered yet."""
    _watch.active, _watch.lost = True, False
    try:
        send(response, header)
    finally:
        _watch.active = False
    return not _watch.lost


@dataclass(order=True)
class _Pending:
    due: float
    order: int
    attempt: Callable[[], bool] = field(compare=False)
    name: str = field(compare=False)
    lost_at: float = field(compare=False)
    log: Any = field(compare=False)
    attempts: int = field(default=1, compare=False)


class Resender:
    """One daemon thread per process that retries lost responses until delivered or too late."""

    def __init__(self, window: float, period: float = RESEND_PERIOD_S) -> None:
        self.window = window
        self.period = period
        self.sent = 0  # responses a retry sent (delivered, or their client had gone)
        self.given_up = 0  # responses still not sent after the window
        self._heap: list[_Pending] = []
        self._cond = threading.Condition()
        self._order = itertools.count()
        self._thread: threading.Thread | None = None

    def add(self, name: str, attempt: Callable[[], bool], log: Any) -> None:
        """Retry ``attempt`` (True = sent) for the response of service ``name``."""
        now = time.monotonic()
        if self.window <= 0:
            log.error(
                f"response of {name} lost: the client is not discovered yet "
                f"({_RESEND_ENV}=0: not sent again)"
            )
            return
        log.warning(
            f"response of {name} not delivered: the client is not discovered yet; "
            f"sending it again for up to {self.window:g} s"
        )
        with self._cond:
            heapq.heappush(
                self._heap, _Pending(now + self.period, next(self._order), attempt, name, now, log)
            )
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="packml-resend", daemon=True)
                self._thread.start()
            self._cond.notify()

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._heap or self._heap[0].due > time.monotonic():
                    self._cond.wait(self._heap[0].due - time.monotonic() if self._heap else None)
                item = heapq.heappop(self._heap)
            self._retry(item)

    def _retry(self, item: _Pending) -> None:
        try:
            sent = item.attempt()
        except Exception as exc:  # the service was destroyed (shutdown): nobody to answer for
            item.log.warning(f"response of {item.name} not delivered: {exc}")
            return
        waited = time.monotonic() - item.lost_at
        if sent:
            self.sent += 1
            item.log.info(
                f"response of {item.name} sent after {waited:.2f} s ({item.attempts + 1} attempts)"
            )
        elif waited >= self.window:
            self.given_up += 1
            item.log.error(
                f"response of {item.name} lost: the client's response reader was not "
                f"discovered within {self.window:g} s ({item.attempts + 1} attempts)"
            )
        else:
            item.attempts += 1
            item.due = time.monotonic() + self.period
            with self._cond:
                heapq.heappush(self._heap, item)


@functools.cache
def resender() -> Resender:
    """The process's resender, created (and the warning hook installed) on first use."""
    window = resend_window()
    _install_hook()
    return Resender(window)


#: The Trigger shortcut of each PackML command (``<node>/reset``, ``<node>/start``, ...): the
#: names every node that takes commands serves (units, PLC bridges, the coordinator).
TRIGGER_SHORTCUTS: tuple[tuple[str, Cmd], ...] = tuple((c.name.lower(), c) for c in Cmd if c)


def create_service(node: Node, srv_type: Any, name: str, callback: Any, **kwargs: Any) -> Any:
    """``node.create_service(...)`` behind the request boundary (:func:`.boundary.guard`), with
    queues for the clients a cell has (:data:`.qos.SERVICES`), whose responses dropped for a
    client discovered late are sent again (see the module docstring). Both rclpy executors send
    through ``send_response``."""
    retries = resender()  # reads PACKML_RESPONSE_RESEND_S now: a bad value fails at start-up
    kwargs.setdefault("qos_profile", qos.SERVICES)
    path = f"{node.get_fully_qualified_name()}/{name[2:]}" if name.startswith("~/") else name
    guarded = boundary.guard(callback, path, node.get_logger())
    service = node.create_service(srv_type, name, guarded, **kwargs)
    send = service.send_response
    log = node.get_logger()

    def send_response(response: Any, header: Any) -> None:
        attempt = functools.partial(send_watched, send, response, header)
        if not attempt():
            retries.add(service.service_name, attempt, log)

    service.send_response = send_response  # type: ignore[method-assign]  # both executors look it up
    return service
