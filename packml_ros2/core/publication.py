"""When the unit publishes what: the output queue and its coalescing.

- A transition is published at once (its record, then the status at it).
- Other status changes (EM progress, alarms, speed, ...) at most every :data:`STATUS_COALESCE`
  seconds: the first change after a publication schedules one.
- The alarm list whenever it changed, after the transition or status that goes with it.
- Admin periodically (``admin_period``) and after discrete changes (transitions, counts, alarms,
  resets) at most every :data:`ADMIN_COALESCE` seconds.

:class:`Publication` owns what the last status and admin showed (keys of version numbers the unit
gives it as callables; a status key starts with the sequence number) and schedules its coalescing
on the unit's :class:`~.deadlines.Deadlines`. The queue is the unit's: the state machine appends
its transition records itself (every transition is published, and its status with it: a status
key whose sequence is behind the unit's means that happened). It builds no message: the queue
holds marks and records; the unit's views (:mod:`.packtags`) are built by the publisher.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple, Protocol

from .deadlines import Deadlines, Due

STATUS_COALESCE = 0.05
ADMIN_COALESCE = 0.25
Key = Callable[[], tuple[int, ...]]


class Versioned(Protocol):
    @property
    def version(self) -> int: ...


class StatusMark(NamedTuple):
    """Where a status publication was due; the unit's ``status_at`` turns it into a view."""

    time: float
    state: int
    sequence: int


class Publication:
    __slots__ = ("_admin_key_of", "_alarms", "_deadlines", "_emit", "_status_key_of",
                 "admin_due", "admin_key", "alarms_seen", "status_due", "status_key")  # fmt: skip

    def __init__(
        self,
        emit: Callable[[tuple[str, Any]], None],
        deadlines: Deadlines,
        status_key: Key,
        admin_key: Key,
        alarms: Versioned,
    ) -> None:
        self._deadlines = deadlines
        self._status_key_of = status_key
        self._admin_key_of = admin_key
        self._alarms = alarms  #: its version changes with the alarm list
        #: Appends to the unit's queue: ("transition", record), ("status", StatusMark), ("alarms",
        #: version), ("admin", view), ("log", (level, text)).
        self._emit = emit
        #: What the last published status showed, starting with its sequence number. A sequence
        #: behind the unit's: a transition was published since, with its status; the key is taken
        #: again when the input ends (or, after a command's fast path, when the next begins).
        self.status_key: tuple[int, ...] = (-1,)
        self.status_due = False
        self.admin_key: tuple[int, ...] = ()
        self.admin_due = False
        self.alarms_seen = -1

    def log(self, level: str, text: str) -> None:
        self._emit(("log", (level, text)))

    # -- status ------------------------------------------------------------------------------------
    def status_now(self, time: float, state: int, sequence: int) -> None:
        """A status now (a mode event, the lamp): not coalesced."""
        self.status_key = self._status_key_of()
        self._emit(("status", StatusMark(time, state, sequence)))
        self.alarms_changed()

    def with_record(self) -> None:
        """A record that keeps the sequence (a mode change) went out with its status: the key is
        taken when the input ends. (Transitions move the sequence: no call needed.)"""
        self.status_key = (-1,)

    def baseline(self) -> None:
        """The status shows what it shows now (after a transition, whose status went out with it;
        nothing changes between inputs)."""
        self.status_key = self._status_key_of()

    def flush(self, now: float, sequence: int) -> None:
        """An input or a deadline is done (the unit at ``sequence``): schedule a status if
        anything it shows changed, the alarm list if it changed, an admin if a discrete change
        happened."""
        if self.status_key[0] != sequence:  # a transition published the status: the baseline
            self.status_key = self._status_key_of()
        elif not self.status_due and self._status_key_of() != self.status_key:
            self.status_due = True
            self._deadlines.at(now + STATUS_COALESCE, Due.STATUS)
        self.alarms_changed()
        if not self.admin_due and self._admin_key_of() != self.admin_key:
            self.admin_due = True
            self._deadlines.at(now + ADMIN_COALESCE, Due.ADMIN_CHANGE)

    def status_deadline(self, time: float, state: int, sequence: int) -> None:
        """The coalescing deadline: publish the status if it still differs."""
        self.status_due = False
        if self._status_key_of() != self.status_key:
            self.status_now(time, state, sequence)

    def alarms_changed(self) -> None:
        """The alarm list is published if it changed since it was last (after each transition
        and at the end of every input)."""
        version = self._alarms.version
        if version != self.alarms_seen:
            self.alarms_seen = version
            self._emit(("alarms", version))

    # -- admin -------------------------------------------------------------------------------------
    def admin(self, view: Any, coalesced: bool) -> None:
        """An admin view is published (periodic, or ``coalesced`` after discrete changes)."""
        if coalesced:
            self.admin_due = False
        self.admin_key = self._admin_key_of()
        self._emit(("admin", view))
