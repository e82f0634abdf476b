"""The engine's own timeline: what is due when (state timeouts, minimum dwell, the mode-change
timeout, the mode-change-not-allowed lamp, coalesced status and admin publications, periodic admin
and saves).

:class:`Deadlines` owns the heap and the time of the earliest deadline (``next_due``, ``inf`` when
none). The unit fires them in time order, each at its own time, so results depend only on the
clock values of its inputs. ``next_due`` is also what a driver may sleep until instead of polling.
"""

from __future__ import annotations

import heapq
import math
from enum import IntEnum
from typing import Any


class Due(IntEnum):
    """The kinds of deadline (a snapshot names them in lower case); each has one handler (``HANDLERS`` of
    :mod:`.deadline_handlers`, the one table from kind to what the unit does)."""

    TIMEOUT = 1  #: a state's timeout (data: (state, sequence))
    DWELL = 2  #: the end of a state's minimum dwell (data: (state, sequence))
    MODE_TIMEOUT = 3  #: a mode change's timeout (data: its sequence)
    STATUS = 4  #: a coalesced status
    LAMP_OFF = 5  #: ``mode_change_not_allowed`` goes out
    ADMIN_CHANGE = 6  #: a coalesced admin
    SAVE = 7  #: the periodic save (data: the period)
    ADMIN = 8  #: the periodic admin (data: the period)
    RECIPE_TIMEOUT = 9  #: a changeover order's timeout (data: the order's number)


#: Periodic deadlines missed by more than this many periods (the clock jumped, e.g. NTP after
#: boot) are not replayed one by one: the next one is the last period point before now.
MAX_CATCH_UP = 100


class Deadlines:
    """A heap of (time, order, kind, data)."""

    __slots__ = ("_counter", "heap", "next_due")

    def __init__(self) -> None:
        self.heap: list[tuple[float, int, Due, Any]] = []
        self.next_due = math.inf  #: the earliest deadline's time, inf when none
        self._counter = 0

    def __len__(self) -> int:
        return len(self.heap)

    def at(self, when: float, kind: Due, data: Any = None) -> None:
        """``kind`` is due at ``when`` (deadlines at the same time fire in the order set)."""
        self._counter += 1
        heapq.heappush(self.heap, (when, self._counter, kind, data))
        self.next_due = self.heap[0][0]

    def pop(self) -> tuple[float, Due, Any]:
        """The earliest deadline: (time, kind, data)."""
        when, _, kind, data = heapq.heappop(self.heap)
        self.next_due = self.heap[0][0] if self.heap else math.inf
        return when, kind, data

    def shift(self, offset: float) -> None:
        """Every deadline ``offset`` seconds later (earlier when negative): the wall clock stepped
        and the engine's timeline moves with it (a uniform shift keeps the heap's order)."""
        self.heap = [(when + offset, n, kind, data) for when, n, kind, data in self.heap]
        self.next_due = self.heap[0][0] if self.heap else math.inf

    def every(self, now: float, behind_to: float, kind: Due, period: float) -> None:
        """The next of a periodic ``kind``: ``period`` after ``now``; if that is already far
        behind ``behind_to`` (the time the unit is being brought to), the last period point
        before it."""
        when = now + period
        behind = behind_to - when
        if behind > MAX_CATCH_UP * period:
            when += period * math.floor(behind / period)
        self.at(when, kind, period)
