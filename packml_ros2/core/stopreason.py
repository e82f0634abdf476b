"""The StopReason (docs/packml.md §7): the first event that took the unit out of Execute (or into
Stopping, Aborting, Holding, Suspending) — an alarm, an interlock, or an operator or remote command
with its source — and the OEE planned-stop rule that reads it.

:class:`StopReasons` owns the current reason and whether the next stop records a new one (armed by
the states of :data:`~.rules.ENTRY` with ``REARM``).
"""

from __future__ import annotations

from .alarms import AlarmEvent, Kind
from .numbers import Mode, State, command_name
from .rules import PLANNED_STOP_STATES, is_remote

#: OMAC stop-reason IDs (Beckhoff E_AlarmID ranges) for stops that were not alarms.
STOP_ID_OPERATOR = 33  # operator action: cycle stop button
STOP_ID_REMOTE = 4006  # out of service: remote stop requested
STOP_ID_SHUTDOWN = 1000  # machine internal, vendor defined: the unit's own process shut down
STOP_ID_CRASH = 1001  # machine internal, vendor defined: its process ended without shutting down


def stopped_as_planned(mode: int, state: int) -> bool:
    """Where a planned stop reason makes a planned stop: Production, stopped
    (:data:`~.rules.PLANNED_STOP_STATES`)."""
    return mode == Mode.PRODUCTION and state in PLANNED_STOP_STATES


def planned_stop(planned_ids: tuple[int, int], reason_id: int, mode: int, state: int) -> bool:
    """The OEE planned-stop rule: :func:`stopped_as_planned`, with a stop reason in
    ``planned_stop_ids`` (OMAC "out of service" 4000..4999 by default)."""
    lo, hi = planned_ids
    return lo <= reason_id <= hi and stopped_as_planned(mode, state)


class StopReasons:
    __slots__ = ("armed", "planned_ids", "planned_reason", "reason")

    def __init__(self, planned_ids: tuple[int, int]) -> None:
        self.reason: AlarmEvent | None = None
        self.armed = True
        self.planned_ids = planned_ids
        self.planned_reason = False  #: the reason's ID is in the planned range

    def record(self, event: AlarmEvent) -> None:
        """A stop happened: its event is the reason if the stop reason was armed."""
        if self.armed:
            self.set(event)
            self.armed = False

    def set(self, event: AlarmEvent | None) -> None:
        self.reason = event
        lo, hi = self.planned_ids
        self.planned_reason = event is not None and lo <= event.id <= hi

    def planned(self, mode: int, state: State) -> bool:
        """Whether the unit is in a planned stop (OEE): :func:`planned_stop`."""
        return self.planned_reason and stopped_as_planned(mode, state)

    @staticmethod
    def of_command(cmd: int, source: str, t: float) -> AlarmEvent:
        """The stop reason of an operator or remote command."""
        stop_id = STOP_ID_REMOTE if is_remote(source) else STOP_ID_OPERATOR
        return AlarmEvent(
            stop_id,
            cmd,
            f"{command_name(cmd)} by {source}",
            0,
            Kind.COMMAND,
            t,
            source=source,
            reaction=cmd,
            trigger=False,
            latched=False,
        )

    @staticmethod
    def of_shutdown(message: str, t: float) -> AlarmEvent:
        """The stop reason of the unit's own process shutting down while producing."""
        return AlarmEvent(
            STOP_ID_SHUTDOWN,
            0,
            message,
            9,
            Kind.EVENT,
            t,
            source="unit",
            trigger=False,
            latched=False,
        )

    @staticmethod
    def of_crash(message: str, t: float) -> AlarmEvent:
        """The stop reason of a unit whose process ended while producing without shutting down
        (a crash, SIGKILL, a power loss): found at its restart (core/durable.py)."""
        return AlarmEvent(
            STOP_ID_CRASH,
            0,
            message,
            9,
            Kind.EVENT,
            t,
            source="unit",
            trigger=False,
            latched=False,
        )

    @staticmethod
    def of_interlock(cmd: int, source: str, detail: str, stop_id: int, t: float) -> AlarmEvent:
        return AlarmEvent(
            stop_id,
            cmd,
            detail or "interlock",
            0,
            Kind.EVENT,
            t,
            source=source,
            reaction=cmd,
            trigger=False,
            latched=False,
        )
