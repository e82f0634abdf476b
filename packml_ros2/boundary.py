"""The service boundary: what a request must be before any handler of this package sees it.

Every service of a unit, a PLC bridge, the coordinator and a simulated EM is created through
:func:`packml_ros2.responses.create_service`, which puts :func:`guard` in front of its handler:

- every string within the bound of its field and printable (:mod:`packml_ros2.core.limits`);
- every array within :data:`~packml_ros2.core.limits.MAX_ITEMS` entries, nested ones too, and the
  text of the whole request within :data:`~packml_ros2.core.limits.MAX_REQUEST_TEXT`;
- a ``source`` of the grammar of the rule book (:func:`packml_ros2.core.rules.source_refusal`:
  a kind a caller may name, lower case, no spaces; empty = the local operator).

A request that is not is answered at once, INVALID_ARGUMENT (or ``success: false`` for a Trigger)
and a sentence naming the field and its bound, never the value: the handler does not run, so
nothing changes and the unit's input log records nothing. Each refusal is logged, escaped and
rate-limited (:class:`~packml_ros2.core.limits.LogLimiter`).

No callback ends a node: a handler that raises (a defect met by a request nobody foresaw) is
answered as a refusal, INVALID_ARGUMENT with "<service> could not handle this request
(<exception type>)"; a topic callback, a timer or a parameter validator that raises is logged and
the node goes on. Every node of this package is a :class:`GuardedNode`, which puts
:func:`contain` around each callback it is given. The log line names the exception, its
message (escaped, cut, URL credentials redacted) and the line of this package it came from, never
a traceback; lines are rate-limited like refusals.
"""

from __future__ import annotations

import array
import functools
import os
import time
import traceback
from collections.abc import Callable
from functools import cache
from typing import Any

from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock
from rclpy.clock_type import ClockType
from rclpy.node import Node

from .core.limits import MAX_ITEMS, MAX_REQUEST_TEXT, LogLimiter, printable, text_problem
from .core.reasons import Reason
from .core.rules import source_refusal
from .core.secrets import redact_urls

#: The log of refused requests, per process: a few lines of a kind, then a count.
_LIMITER = LogLimiter()
#: The log of callbacks that raised, per process.
_FAILURES = LogLimiter()
#: Characters of an exception's message kept in its log line.
MAX_EXCEPTION_TEXT = 200
_PACKAGE = os.path.dirname(os.path.abspath(__file__))


class _Refused(Exception):
    pass


def _walk(value: Any, field: str, budget: list[int]) -> None:
    """Check ``value`` (of field ``field``): raise :class:`_Refused` with the problem."""
    if isinstance(value, str):
        problem = text_problem(field, value)
        if problem is None and field == "source":
            problem = source_refusal(value)
        if problem is not None:
            raise _Refused(problem)
        budget[0] -= len(value)
        if budget[0] < 0:
            raise _Refused(f"the request holds more than {MAX_REQUEST_TEXT} characters of text")
    elif isinstance(value, list | tuple | array.array):
        if len(value) > MAX_ITEMS:
            raise _Refused(f"{field} has {len(value)} entries (at most {MAX_ITEMS})")
        for item in value:
            _walk(item, field, budget)
    elif hasattr(value, "get_fields_and_field_types"):
        for name in _fields(type(value)):  # type: ignore[arg-type]  # (a message type: hashable)
            _walk(getattr(value, name), name, budget)


@cache
def _fields(msg_type: type) -> tuple[str, ...]:
    """The fields of a message type that can hold text or entries (strings, arrays, messages)."""
    return tuple(
        name
        for name, kind in msg_type.get_fields_and_field_types().items()  # type: ignore[attr-defined]
        if "string" in kind or "sequence" in kind or "[" in kind or "/" in kind
    )


def problem_of(request: Any) -> str | None:
    """Why ``request`` does not pass the boundary (None: it does)."""
    try:
        _walk(request, "request", [MAX_REQUEST_TEXT])
    except _Refused as exc:
        return str(exc)
    return None


def refusal(response: Any, text: str) -> Any:
    """``response`` as a refusal for INVALID_ARGUMENT with ``text``, whatever its type has of
    ``accepted``/``success``, ``result`` and ``message``/``message_out``."""
    for flag in ("accepted", "success"):
        if hasattr(response, flag):
            setattr(response, flag, False)
    if hasattr(response, "result"):
        response.result = int(Reason.INVALID_ARGUMENT)
    for name in ("message", "message_out"):
        if hasattr(response, name):
            setattr(response, name, text)
            break
    return response


def guard(
    callback: Callable[[Any, Any], Any],
    service: str,
    log: Any,
    clock: Callable[[], float] = time.monotonic,
) -> Callable[[Any, Any], Any]:
    """``callback`` behind the boundary: refused requests never reach it."""

    def guarded(request: Any, response: Any) -> Any:
        problem = problem_of(request)
        if problem is None:
            try:
                return callback(request, response)
            except Exception as exc:
                failed(service, exc, log, clock)
                return refusal(type(response)(), handler_failure(service, exc))
        text = f"refused: {problem}"
        write, summary = _LIMITER.admit(f"{service} {problem}", clock())
        if summary is not None:
            log.warning(summary)
        if write:
            log.warning(printable(f"request to {service} {text}"))
        return refusal(response, text)

    return guarded


# -- callbacks that raise --------------------------------------------------------------------------
def handler_failure(service: str, exc: BaseException) -> str:
    """What the caller of ``service`` is told when its handler raised ``exc`` (the type only)."""
    return f"refused: {service} could not handle this request ({type(exc).__name__}); see its log"


def _origin(exc: BaseException) -> str:
    """``file:line`` of the innermost frame of this package the exception passed (else the
    innermost frame), relative to the package."""
    frames = traceback.extract_tb(exc.__traceback__)
    ours = [f for f in frames if os.path.abspath(f.filename).startswith(_PACKAGE)]
    if not (ours or frames):
        return "?"
    frame = (ours or frames)[-1]
    name = os.path.abspath(frame.filename)
    shown = (
        os.path.relpath(name, os.path.dirname(_PACKAGE))
        if name.startswith(_PACKAGE)
        else os.path.basename(name)
    )
    return f"{shown}:{frame.lineno}"


def failed(
    what: str, exc: BaseException, log: Any, clock: Callable[[], float] = time.monotonic
) -> None:
    """Log that the callback ``what`` raised ``exc``: one line, bounded and rate-limited."""
    text = printable(redact_urls(str(exc)), MAX_EXCEPTION_TEXT)
    line = f"{what} failed: {type(exc).__name__}: {text} (at {_origin(exc)}); the node goes on"
    write, summary = _FAILURES.admit(f"{what} {type(exc).__name__}", clock())
    if summary is not None:
        log.error(summary)
    if write:
        log.error(printable(line, 600))


def contain(callback: Callable[..., Any], what: str, log: Any) -> Callable[..., Any]:
    """``callback`` that logs (:func:`failed`) instead of raising: a topic or timer callback."""
    if getattr(callback, "_packml_contained", False):
        return callback

    @functools.wraps(callback)  # (rclpy reads the signature: message info, timer info)
    def contained(*args: Any) -> Any:
        try:
            return callback(*args)
        except Exception as exc:
            failed(what, exc, log)
            return None

    contained._packml_contained = True  # type: ignore[attr-defined]
    return contained


def contain_service(
    callback: Callable[[Any, Any], Any], service: str, log: Any
) -> Callable[[Any, Any], Any]:
    """``callback`` of ``service`` answering a refusal instead of raising."""
    if getattr(callback, "_packml_contained", False):
        return callback

    @functools.wraps(callback)
    def contained(request: Any, response: Any) -> Any:
        try:
            return callback(request, response)
        except Exception as exc:
            failed(service, exc, log)
            return refusal(type(response)(), handler_failure(service, exc))

    contained._packml_contained = True  # type: ignore[attr-defined]
    return contained


class GuardedNode(Node):
    """rclpy's Node whose callbacks cannot end it: every subscription, timer, service and
    parameter validator it is given is wrapped by :func:`contain` (services by
    :func:`contain_service`). Every node of this package is one."""

    def create_subscription(
        self, msg_type: Any, topic: str, callback: Any, qos_profile: Any, **kwargs: Any
    ) -> Any:
        where = f"topic {topic} of {self.get_fully_qualified_name()}"
        return super().create_subscription(
            msg_type, topic, contain(callback, where, self.get_logger()), qos_profile, **kwargs
        )

    def create_timer(
        self, timer_period_sec: float, callback: Any, *args: Any, **kwargs: Any
    ) -> Any:
        """rclpy's timer on a clock that never steps (an NTP step of the wall clock neither
        silences a timer nor fires it early), unless the node runs on simulated time or the
        caller names a clock."""
        if callback is not None:
            callback = contain(
                callback, f"a timer of {self.get_fully_qualified_name()}", self.get_logger()
            )
        if len(args) < 2 and "clock" not in kwargs and not self.uses_sim_time():
            kwargs["clock"] = self._steady_clock()
        return super().create_timer(timer_period_sec, callback, *args, **kwargs)

    def uses_sim_time(self) -> bool:
        """Whether the node's clock follows ``/clock`` (parameter ``use_sim_time``, which rclpy's
        time source applies to the clock: one attribute read, on the path of every EM report)."""
        return bool(getattr(self.get_clock(), "ros_time_is_active", False))

    def steady(self) -> float:
        """Seconds on the clock of the node's own leases and waits: monotonic (it never steps
        with the wall clock); the node's ROS clock under simulated time. Timestamps stay on the
        ROS clock (wall time)."""
        if self.uses_sim_time():
            return float(self.get_clock().now().nanoseconds) * 1e-9
        return time.monotonic()

    def _steady_clock(self) -> Clock:
        clock: Clock | None = self.__dict__.get("_packml_steady_clock")
        if clock is None:
            clock = self.__dict__["_packml_steady_clock"] = Clock(clock_type=ClockType.STEADY_TIME)
        return clock

    def create_service(self, srv_type: Any, srv_name: str, callback: Any, **kwargs: Any) -> Any:
        where = (
            f"{self.get_fully_qualified_name()}/{srv_name[2:]}"
            if srv_name.startswith("~/")
            else srv_name
        )
        return super().create_service(
            srv_type, srv_name, contain_service(callback, where, self.get_logger()), **kwargs
        )

    def add_on_set_parameters_callback(self, callback: Any) -> None:
        log = self.get_logger()
        what = f"a parameter check of {self.get_fully_qualified_name()}"

        @functools.wraps(callback)
        def contained(parameters: Any) -> Any:
            try:
                return callback(parameters)
            except Exception as exc:
                failed(what, exc, log)
                return SetParametersResult(
                    successful=False, reason=f"{what} failed ({type(exc).__name__})"
                )

        super().add_on_set_parameters_callback(contained)
