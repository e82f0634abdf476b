"""EM reports as hostile input (``<unit>/em_reports``): what a report may say, and which writer may
speak for an EM.

:func:`report_problem` checks every field of every kind of report before the unit looks at it:
the EM name (a ROS name), the kind, the lease every report announces, the state (1..17) and
the sequence (none from the future) of State Complete, the command of a request, the counter kind,
index and increment of a count, the ID, category and text of an alarm. A report that fails is
refused, counted and logged (rate-limited); the engine never sees it, so it changes nothing and
the input log records nothing.

:class:`Writers` binds each EM name to the DDS writer (publisher GID) its reports come from. A
report for that name from another writer is refused while the bound writer is alive: a forged
State Complete cannot end an acting state early, a forged Leave cannot make the unit lose an EM.
The binding moves to a new writer when the old one has left the graph (the EM's process ended),
and is released when the EM is lost (its lease expired: an EM restarted after a crash is heard
from then on) or leaves. Silence alone moves nothing: a forger flooding the topic delays the
real EM's heartbeats at the unit, and must not take the name over for that.

What remains unprotected: DDS on the domain is unauthenticated (the pinned Fast DDS wheels have
no DDS Security). A writer that speaks for an EM name first — before the EM, or while it is down —
is the EM for the unit until it is lost or leaves. Only SROS2
(authenticated, access-controlled DDS) closes that: see the README's security section.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from .counters import KINDS as COUNTER_KINDS
from .limits import MAX_NAME, text_problem
from .numbers import Cmd, State
from .rules import NUM_CATEGORIES

#: EmReport.KIND_* -> name (packml_interfaces/msg/EmReport; a test keeps them equal).
KINDS = ("heartbeat", "state_complete", "command_request", "interlock", "count", "alarm", "leave",
         "recipe")  # fmt: skip
HEARTBEAT, STATE_COMPLETE, COMMAND_REQUEST, INTERLOCK, COUNT, ALARM, LEAVE, RECIPE = range(
    len(KINDS)
)
#: The longest lease a heartbeat may announce (seconds).
MAX_LEASE = 3600.0
_FIRST = frozenset("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz_")
_REST = _FIRST | frozenset("0123456789")
_STATES = frozenset(int(s) for s in State if s)


def name_problem(name: str) -> str | None:
    """Why ``name`` is not an EM name (a ROS name: ASCII letters, digits, ``_``, not starting
    with a digit; at most :data:`~.limits.MAX_NAME`)."""
    problem = text_problem("em", name, MAX_NAME)
    if problem is not None:
        return problem
    if not name or name[0] not in _FIRST or not _REST.issuperset(name):
        return "em is not a ROS name (A-Z a-z 0-9 _, not starting with a digit)"
    return None


def report_problem(msg: Any, sequence: int) -> str | None:
    """Why the report ``msg`` (an ``EmReport``) is refused (None: every field is plausible);
    ``sequence``: the unit's transition sequence number now."""
    problem = name_problem(msg.em)
    if problem is not None:
        return problem
    if not (math.isfinite(msg.lease) and 0 <= msg.lease <= MAX_LEASE):
        return f"lease {msg.lease} is not 0 .. {MAX_LEASE:g} s"
    kind = msg.kind
    if kind in (HEARTBEAT, LEAVE):
        return None
    if kind == STATE_COMPLETE:
        if msg.state not in _STATES:  # (a wait state too: EMs confirm mode changes so)
            return f"State Complete for state {msg.state}, which is not a state (1..17)"
        if msg.sequence > sequence:
            return f"State Complete for sequence {msg.sequence}, ahead of the unit's {sequence}"
        return None
    if kind == COMMAND_REQUEST:
        if not 0 <= msg.command <= max(Cmd):
            return f"command {msg.command} is not 0 (withdraw) .. {int(max(Cmd))}"
        return None
    if kind == INTERLOCK:
        return None  # two flags and a bit set: every value means something
    if kind == COUNT:
        if msg.counter >= len(COUNTER_KINDS):
            return f"counter {msg.counter} is not 0 .. {len(COUNTER_KINDS) - 1} ({', '.join(COUNTER_KINDS)})"
        if msg.counter_index < 0 or msg.increment < 0:
            return f"count index {msg.counter_index} and increment {msg.increment} must be >= 0"
        return None
    if kind == ALARM:
        if msg.alarm_id <= 0:
            return f"alarm ID {msg.alarm_id} is not 1 .. 2^31-1"
        if not -1 <= msg.category < NUM_CATEGORIES:
            return (
                f"category {msg.category} is neither -1 (as configured) nor 0..{NUM_CATEGORIES - 1}"
            )
        return text_problem("message", msg.message)
    if kind == RECIPE:  # (the order's number is checked by the unit: a stale one changes nothing)
        return text_problem("message", msg.message)
    return f"kind {kind} is not a report kind (0..{len(KINDS) - 1}: {', '.join(KINDS)})"


class Writers:
    """EM name -> the writer (an opaque ID: the DDS publisher GID) its reports are taken from, on
    the caller's clock (the time of its last report, for the refusal's sentence)."""

    def __init__(self) -> None:
        self._bound: dict[str, list[Any]] = {}  # name -> [writer, last report time]
        self.refused = 0

    def claim(
        self, name: str, writer: bytes, now: float, gone: Callable[[bytes], bool] | None = None
    ) -> tuple[bool, str | None]:
        """A report for ``name`` from ``writer`` at ``now``: whether to take it, and a note for
        the log (a writer taking the name over, or a refusal). ``gone(w)``: whether writer ``w``
        has left the graph (asked only when another writer reports)."""
        bound = self._bound.get(name)
        if bound is None:
            self._bound[name] = [writer, now]
            return True, None
        if bound[0] == writer:
            bound[1] = now
            return True, None
        silent = now - bound[1]
        if gone is not None and gone(bound[0]):
            self._bound[name] = [writer, now]
            return True, f"EM {name} reports from a new writer (its writer left: restarted)"
        self.refused += 1
        return False, (
            f"report for EM {name} from another writer refused: {name} reports from one writer, "
            f"heard {silent:.1f} s ago and still on the graph (two nodes with one name, or a forger)"
        )

    def release(self, name: str) -> None:
        """``name`` was lost or left: the next writer to report for it is the EM."""
        self._bound.pop(name, None)

    def bound(self, name: str) -> bytes | None:
        entry = self._bound.get(name)
        return None if entry is None else bytes(entry[0])

    def __len__(self) -> int:
        return len(self._bound)


__all__ = ["KINDS", "MAX_LEASE", "Writers", "name_problem", "report_problem"]
