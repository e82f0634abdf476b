"""What survives a restart of a unit (docs/packml.md §6): its admin data, never its state.

:class:`Durable` links the unit's parts (times, counters, alarms, stop reason) to its
:class:`~.persistence.Store`: the snapshot document (:meth:`Durable.document`), the journal of each
input's changes, written before the unit answers or publishes (:meth:`Durable.journal`:
write-ahead), and the restore at start-up (:meth:`Durable.restore`). It remembers what it last
wrote, so an input journals only what changed: counters, alarm occurrences (by serial), the stop
reason, the machine speed, and the sequence and times after state and mode changes.

Two things a process killed between inputs (SIGKILL, a crash) would otherwise lose:

- **time**: times accumulate between inputs, so the unit node journals them every
  :data:`TIME_CHECKPOINT` seconds (:meth:`Durable.checkpoint`, one ``write()``): a killed unit
  loses at most that much of its mode and state times (plus the executor's delay of the timer);
- **why it stopped**: ``producing`` is journaled with every change of it (the unit is in Execute
  or on its way there, and its StopReason is armed). A unit that restores ``producing`` true
  did not shut down (a shutdown records its StopReason first): it crashed, and that is its
  StopReason now (:data:`~.stopreason.STOP_ID_CRASH`, unplanned), not the last stop's.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

from .alarms import AlarmEvent, AlarmManager
from .counters import Counters
from .persistence import NotWritten, one_line
from .stopreason import StopReasons
from .times import ModeStateTimes


class StoreLike(Protocol):
    """A :class:`~.persistence.Store`, or a stand-in (replay's, which writes nothing)."""

    def load(self) -> dict[str, Any] | None: ...
    def save(self, document: dict[str, Any], now: float) -> None: ...
    def close(self) -> None: ...


@dataclass
class Restored:
    """What a unit restored: the document (None: nothing stored) and what went wrong."""

    document: dict[str, Any] | None
    sequence: int = 0
    mach_speed: float | None = None
    recipe: int | None = None  #: RecipeCurrent's ID (None: the store has none)
    problems: list[str] = field(default_factory=list)
    #: the unit was producing when it last journaled: it ended without shutting down
    producing: bool = False


#: s: the unit node journals the times this often (what a SIGKILL loses of them at most).
TIME_CHECKPOINT = 1.0


def document(
    times: ModeStateTimes,
    counters: Counters,
    alarms: AlarmManager,
    stops: StopReasons,
    sequence: int,
    mach_speed: float,
    now: float,
    producing: bool = False,
    recipe: int = 0,
) -> dict[str, Any]:
    """What persistence stores of a unit: everything of the admin data, never the state (only
    whether it was ``producing``: see the module docstring)."""
    stop_reason = stops.reason
    return {
        "sequence": sequence,
        "times": times.to_dict(now),
        "counters": counters.to_dict(),
        "alarms": alarms.to_dict(),
        "stop_reason": stop_reason.to_dict() if stop_reason else None,
        "mach_speed": mach_speed,
        "recipe_current": recipe,
        "saved_at": now,
        "producing": producing,
    }


#: Seconds between tries to write a store that failed (a full disk): each try is a snapshot.
RETRY = 1.0


class Durable:
    """The admin data's persistence. A write that fails (a full disk) does not stop the unit:
    :attr:`failing` says why (the unit raises its ``persistence_failing`` alarm and says in its
    answers that they are not durable), no journal record is written after a lost one (its
    changes would be missing under them), and a snapshot, which holds everything, is tried every
    :data:`RETRY` seconds until one is written: then the store is whole again."""

    __slots__ = (
        "_append",
        "_producing",
        "_recipe",
        "_retry_at",
        "_written",
        "alarms",
        "counters",
        "failing",
        "stops",
        "store",
        "times",
    )

    def __init__(
        self,
        store: StoreLike,
        times: ModeStateTimes,
        counters: Counters,
        alarms: AlarmManager,
        stops: StopReasons,
        producing: Callable[[], bool] = lambda: False,
        recipe: Callable[[], int] = lambda: 0,
    ) -> None:
        self.store = store
        self._recipe = recipe  #: RecipeCurrent's ID now
        self._producing = producing  #: whether the unit is producing now (module docstring)
        #: None for a store that keeps no journal (a replay's): journal() then only forgets
        self._append = getattr(store, "append", None)
        self.times, self.counters, self.alarms, self.stops = times, counters, alarms, stops
        #: (sequence, mode, times resets, counters version, stop reason, speed, producing) as
        #: last written
        self._written: tuple[Any, ...] = ()
        #: why the admin data is not on the disk ('' = it is): what the unit answered since is
        #: in memory only until a snapshot is written
        self.failing: str = getattr(store, "failing", "") or ""
        self._retry_at = -float("inf")
        alarms.take_changed()  # from now on the alarms note which occurrences change

    def document(self, sequence: int, mach_speed: float, now: float) -> dict[str, Any]:
        """The snapshot: everything of the admin data, never the state."""
        return document(
            self.times,
            self.counters,
            self.alarms,
            self.stops,
            sequence,
            mach_speed,
            now,
            self._producing(),
            self._recipe(),
        )

    def snapshot(
        self, sequence: int, mode: int, mach_speed: float, now: float, closing: bool = False
    ) -> None:
        """The snapshot; ``closing``: the unit's last, at an orderly end (never a crash, so it
        is not ``producing`` whatever its state)."""
        document = self.document(sequence, mach_speed, now)
        if closing:
            document["producing"] = False
        try:
            self.store.save(document, now)
        except NotWritten as exc:
            self._failed(str(exc), now)
            return
        self.failing = ""
        self.alarms.take_changed()
        self._written = self._state(sequence, mode, mach_speed)

    def _failed(self, why: str, now: float) -> None:
        self.failing = why
        self._retry_at = now + RETRY

    def shift(self, offset: float) -> None:
        """The clock stepped by ``offset``: a pending retry keeps its delay."""
        self._retry_at += offset

    def _state(self, sequence: int, mode: int, mach_speed: float) -> tuple[Any, ...]:
        times, counters, stops = self.times, self.counters, self.stops
        return (
            sequence,
            mode,
            times.resets,
            counters.version,
            stops.reason,
            mach_speed,
            self._producing(),
            self._recipe(),
        )

    def checkpoint(self, now: float) -> None:
        """Journal the times as of ``now`` (one ``write()``; not an input: nothing changes)."""
        if self._append is None or self.failing:  # (failing: the retried snapshot holds them)
            return
        try:
            self._append([{"set": {"times": self.times.to_dict(now), "saved_at": now}}])
        except NotWritten as exc:
            self._failed(str(exc), now)

    def journal(self, sequence: int, mode: int, mach_speed: float, now: float) -> None:
        """Write what changed since the last call (one ``write()``): before the unit answers."""
        changed = self.alarms.changed
        if self._append is None:
            if changed:
                changed.clear()
            return
        if self.failing:
            if changed:
                changed.clear()  # (the snapshot holds every occurrence)
            if now >= self._retry_at:  # a snapshot holds all the journal would
                self.snapshot(sequence, mode, mach_speed, now)
            return
        state = self._state(sequence, mode, mach_speed)
        if state == self._written and not changed:
            return
        records: list[dict[str, Any]] = []
        written = self._written or (None,) * len(state)
        changes: dict[str, Any] = {}
        if state[:3] != written[:3]:  # a state or mode change, a reset: times and sequence
            changes["sequence"] = sequence
            changes["times"] = self.times.to_dict(now)
            changes["saved_at"] = now
        if state[3] != written[3]:
            changes["counters"] = self.counters.to_dict()
        if state[4] is not written[4]:
            changes["stop_reason"] = state[4].to_dict() if state[4] is not None else None
        if state[5] != written[5]:
            changes["mach_speed"] = mach_speed
        if state[6] != written[6]:
            changes["producing"] = state[6]
        if state[7] != written[7]:
            changes["recipe_current"] = state[7]
        if changes:
            records.append({"set": changes})
        alarms = self.alarms
        dropped, keep = alarms.history_dropped, alarms.history_capacity
        records += [
            {"event": ev.to_dict(), "dropped": dropped, "keep": keep}
            for ev in alarms.take_changed()
        ]
        if records:
            try:
                self._append(records)
            except NotWritten as exc:
                self._failed(str(exc), now)
                return
        self._written = state

    def restore(self, now: float) -> Restored:
        """Load the stored admin data into the parts (the unit sets the sequence and speed)."""
        data = self.store.load()
        problems = list(getattr(self.store, "problems", []))
        out = Restored(data, problems=problems)
        if data is None:
            return out
        try:
            out.sequence = int(data.get("sequence", 0))
            self.times.restore(data.get("times", {}), now)
            self.counters.restore(data.get("counters", {}))
            self.alarms.restore(data.get("alarms", {}))
            if data.get("stop_reason"):
                self.stops.set(AlarmEvent.from_dict(data["stop_reason"]))
            out.mach_speed = float(data.get("mach_speed", 0.0))
            out.producing = data.get("producing") is True
            out.recipe = int(data.get("recipe_current", 0))
        except (TypeError, ValueError, KeyError) as exc:
            problems.append(
                f"the stored admin data could not be restored ({one_line(exc)}): the unit starts without it"
            )
        self.alarms.take_changed()
        return out
