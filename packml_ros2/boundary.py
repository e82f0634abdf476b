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
"""

from __future__ import annotations

import array
import time
from collections.abc import Callable
from functools import cache
from typing import Any

from .core.limits import MAX_ITEMS, MAX_REQUEST_TEXT, LogLimiter, printable, text_problem
from .core.reasons import Reason
from .core.rules import source_refusal

#: The log of refused requests, per process: a few lines of a kind, then a count.
_LIMITER = LogLimiter()


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
        for name in _fields(type(value)):
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


def guard(callback: Callable[[Any, Any], Any], service: str, log: Any,
          clock: Callable[[], float] = time.monotonic) -> Callable[[Any, Any], Any]:  # fmt: skip
    """``callback`` behind the boundary: refused requests never reach it."""

    def guarded(request: Any, response: Any) -> Any:
        problem = problem_of(request)
        if problem is None:
            return callback(request, response)
        text = f"refused: {problem}"
        write, summary = _LIMITER.admit(f"{service} {problem}", clock())
        if summary is not None:
            log.warning(summary)
        if write:
            log.warning(printable(f"request to {service} {text}"))
        return refusal(response, text)

    return guarded
