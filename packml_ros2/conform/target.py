"""What ``packml conform`` needs of a target, whatever its face (a ROS unit, an OPC 30050
server): its state and mode as it shows them, every state it showed, its answers to commands
and mode changes, its Admin PackTags. :mod:`.ros_target` and :mod:`.opcua_target` implement it.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

from ..core.numbers import NUM_STATES, State


class Unreachable(Exception):
    """The target cannot be reached or did not answer: why, in a sentence."""


@dataclass(frozen=True)
class Reply:
    """A target's answer to a command, a mode change or a reset.

    ``accepted``; ``code``: the reason code's name where the face has reason codes (ROS:
    ``COMMAND_NOT_ALLOWED``...), the status code's name on OPC UA (``BadInvalidState``);
    ``reason``: the number of a ROS reason code (None where the face has none); ``text``: the
    target's sentence."""

    accepted: bool
    code: str
    text: str = ""
    reason: int | None = None


@dataclass(frozen=True)
class Shown:
    """One state or mode the target showed: when (the runner's clock), state, mode."""

    at: float
    state: State
    mode: int
    sequence: int | None = None  #: the target's transition sequence number, where it shows one


@dataclass(frozen=True)
class AdminView:
    """The Admin PackTags of one moment: times in whole seconds, flattened as in
    ``packml_interfaces/msg/Admin`` (``state_*[mode * NUM_STATES + state]``); counts as
    (count, acc_count) per counter of ProdProcessedCount, ProdDefectiveCount and
    ProdConsumedCount. ``at``: when it was taken, on the target's clock where it has one
    (seconds), else on the runner's; ``received``: when it reached the runner (its clock)."""

    at: float
    received: float
    state_current_time: Sequence[int] = ()
    state_cumulative_time: Sequence[int] = ()
    mode_current_time: Sequence[int] = ()
    mode_cumulative_time: Sequence[int] = ()
    counts: Sequence[tuple[int, int]] = ()

    def state_time(self, mode: int, state: State, cumulative: bool = False) -> int | None:
        values = self.state_cumulative_time if cumulative else self.state_current_time
        index = mode * NUM_STATES + int(state)
        return int(values[index]) if 0 <= index < len(values) else None

    def mode_time(self, mode: int, cumulative: bool = False) -> int | None:
        values = self.mode_cumulative_time if cumulative else self.mode_current_time
        return int(values[mode]) if 0 <= mode < len(values) else None


@dataclass(frozen=True)
class Tags:
    """The Status PackTags the run compares with what the standard says: state and mode as the
    tags show them, and what a face shows beside them (None where it shows nothing):
    ``StatesDisabled`` of the current mode, the commands valid now, the transition sequence
    number."""

    state: State | None
    mode: int
    disabled_mask: int | None = None
    commands_valid: tuple[int, ...] | None = None
    sequence: int | None = None


class Target(Protocol):
    """A PackML target as the conformance run drives it."""

    #: the target, for people: ``ROS unit /cell/filler`` or ``opc.tcp://... PackMLObjects/x``
    where: str
    #: which face: "ros" or "opcua"
    face: str
    #: whether every state the target passes through reaches :meth:`shown` (a transition
    #: stream); else some may be coalesced and only what was shown is checked
    complete_path: bool

    def connect(self, timeout: float) -> None:
        """Reach the target and read its state and mode (raises :class:`Unreachable`)."""

    def close(self) -> None: ...

    def shown(self) -> History:
        """Every state and mode shown since :meth:`connect`."""

    def command(self, cmd: int, timeout: float) -> Reply: ...

    def set_mode(self, mode: int, timeout: float) -> Reply: ...

    def admin(self, newer_than: float | None, timeout: float) -> AdminView | None:
        """The Admin PackTags, received after ``newer_than`` (the runner's clock) when given,
        waiting up to ``timeout``; None when none came (or the face has none)."""

    def reset_counters(self, timeout: float) -> Reply | None:
        """Reset the production counters; None when the face has no way to."""

    def tags(self) -> Tags | None:
        """The Status PackTags as last shown (None: the target has shown none yet)."""


@dataclass
class History:
    """What a target showed, in order, with waiting (thread-safe: faces append from their own
    threads). Consecutive duplicates are dropped."""

    clock: Callable[[], float] = time.monotonic
    items: list[Shown] = field(default_factory=list)
    _cond: threading.Condition = field(default_factory=threading.Condition)

    def add(self, state: State, mode: int, sequence: int | None = None) -> None:
        with self._cond:
            if self.items and (self.items[-1].state, self.items[-1].mode) == (state, mode):
                return
            self.items.append(Shown(self.clock(), state, mode, sequence))
            del self.items[:-10_000]  # bounded
            self._cond.notify_all()

    def mark(self) -> int:
        """The number of entries so far (for :meth:`since`)."""
        with self._cond:
            return len(self.items)

    def since(self, mark: int) -> list[Shown]:
        with self._cond:
            return list(self.items[mark:])

    @property
    def last(self) -> Shown | None:
        with self._cond:
            return self.items[-1] if self.items else None

    def wait(self, predicate: Callable[[Shown], bool], timeout: float) -> Shown | None:
        """The newest entry once ``predicate`` holds for it (None after ``timeout``)."""
        deadline = self.clock() + timeout
        with self._cond:
            while True:
                if self.items and predicate(self.items[-1]):
                    return self.items[-1]
                remaining = deadline - self.clock()
                if remaining <= 0:
                    return None
                self._cond.wait(min(remaining, 0.05))

    def wait_change(self, mark: int, timeout: float) -> bool:
        """Whether anything was shown after ``mark`` within ``timeout``."""
        deadline = self.clock() + timeout
        with self._cond:
            while len(self.items) <= mark:
                remaining = deadline - self.clock()
                if remaining <= 0:
                    return False
                self._cond.wait(min(remaining, 0.05))
            return True
