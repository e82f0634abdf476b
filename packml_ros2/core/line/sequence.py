"""Cell commands and mode changes as state machines the coordinator node drives.

A run is asked :meth:`Run.next` (``now``, and whether a unit's service is there): it answers the
calls to make now and how long to wait for news, or its :class:`Outcome`. The node makes the
calls and hands each answer to :meth:`Run.answer`; news of the units (the :class:`~.cell.Cell`)
and cancellations wake it. Nothing here blocks or reads a clock.

Sequencing: start-like commands (RESET, START, UNHOLD, UNSUSPEND, CLEAR) go to the units in
``start_order``, stop-like ones (STOP, HOLD, SUSPEND, COMPLETE) in ``stop_order``. Each step waits
until the unit reached the state its answer names as ``state_requested`` before the next unit is
commanded; a unit already in (or on its way to) the command's target state — the rule book's
(:meth:`~..rules.Rules.command_target`) — is skipped. All or nothing: before any unit is
commanded, every unit is checked (:meth:`.Cell.refusals`); one that cannot take it refuses the
command for the cell. STOP goes to every unit that can stop (one that cannot is skipped, one that
refuses is reported, the others stop all the same). A unit that refuses anyway, a step longer
than ``step_timeout`` or a lost unit ends the sequence; the answer names the unit and quotes its
reason. ABORT goes to every unit at once. A mode change is all or nothing too: a unit that refuses
anyway has the units changed before it changed back.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from ..numbers import Cmd, State, state_name
from ..reasons import Reason
from .cell import SOURCE, Cell, UnitView

START_LIKE = frozenset({Cmd.RESET, Cmd.START, Cmd.UNHOLD, Cmd.UNSUSPEND, Cmd.CLEAR})
STOP_LIKE = frozenset({Cmd.STOP, Cmd.HOLD, Cmd.SUSPEND, Cmd.COMPLETE})
POLL = 0.5  # s: the longest a run waits without news
#: The cell commands taken while a sequence runs: each interrupts it (ABORT goes to every unit
#: beside it, STOP cancels it and then runs); any other is refused as busy until it has ended.
INTERRUPTS_A_SEQUENCE: tuple[Cmd, ...] = (Cmd.STOP, Cmd.ABORT)
SERVICE_POLL = 0.02  # s between looks for a service not discovered yet

Ready = Callable[[str, str], bool]  #: (unit, service) -> is it there


@dataclass(frozen=True)
class Outcome:
    accepted: bool
    result: int
    message: str
    mode: int = 0  #: mode runs: the mode the cell has now (0: mixed)
    busy: bool = False  #: refused because another sequence runs (not a fault of the request)


@dataclass(frozen=True)
class StopWaits:
    """A cell STOP asked while another sequence runs: that sequence is cancelled and the STOP
    begins once it has ended; ask again (``Line.begin_command(..., asked=since)``) when a run
    ends, at the latest after ``poll`` seconds. ``since``: when the STOP was first asked."""

    since: float
    poll: float = POLL


@dataclass(frozen=True)
class UnitCall:
    unit: str
    service: str
    fields: Mapping[str, Any]


@dataclass(frozen=True)
class Answer:
    """What a unit answered (``error``: the call failed: no answer, not reachable)."""

    accepted: bool = False
    result: int = 0
    message: str = ""
    state_current: int = 0
    state_requested: int = 0
    error: str | None = None


class Failed(Exception):
    def __init__(self, result: int, message: str) -> None:
        super().__init__(message)
        self.result = result
        self.message = message


@dataclass
class _Call:
    """A call of one unit's service in progress: waits for the service, then for the answer."""

    unit: str
    service: str
    fields: dict[str, Any]
    deadline: float
    sent: bool = False
    answer: Answer | None = None


@dataclass
class _Wait:
    """Waiting for a unit to reach ``target`` after sequence ``seq0`` (``cmd``: from that
    command's own transition on)."""

    unit: str
    cmd: Cmd | None
    seq0: int
    target: int
    deadline: float


class Run:
    """Base of the runs: cancellation, calls, waits."""

    def __init__(self, cell: Cell, name: str) -> None:
        self.cell = cell
        self.name = name
        self.step = f"{name}: starting"  #: what it waits for (CellStatus.sequence_step)
        self.cancelled_by: str | None = None
        self.outcome: Outcome | None = None
        self.timeout = cell.coordinator.step_timeout

    def cancel(self, by: str) -> None:
        if self.cancelled_by is None:
            self.cancelled_by = by

    def next(self, now: float, ready: Ready) -> tuple[list[UnitCall], float] | Outcome:
        raise NotImplementedError

    def answer(self, unit: str, service: str, answer: Answer) -> None:
        raise NotImplementedError

    # -- pieces ------------------------------------------------------------------------------------
    def _check(self, unit: UnitView, now: float, cancellable: bool = True) -> None:
        if cancellable and self.cancelled_by is not None:
            raise Failed(Reason.SUPERSEDED, f"cancelled at {unit.name} by {self.cancelled_by}")

    def _online(self, unit: UnitView, now: float) -> None:
        if not unit.online or unit.status is None:
            raise Failed(Reason.UNIT_UNAVAILABLE, self.cell.offline_text(unit, now))

    def _poll_call(
        self, call: _Call, now: float, ready: Ready, out: list[UnitCall], cancellable: bool = True
    ) -> float:
        """Advance ``call``: the calls to send go to ``out``; the time to wait (raises Failed)."""
        unit = self.cell.units[call.unit]
        self._check(unit, now, cancellable)
        self._online(unit, now)
        if not call.sent and ready(call.unit, call.service):
            call.sent = True
            out.append(UnitCall(call.unit, call.service, call.fields))
        if now >= call.deadline:
            what = "did not answer" if call.sent else "is not available"
            raise Failed(
                Reason.UNIT_UNAVAILABLE,
                f"{call.unit}/{call.service} {what} within {self.timeout:g} s",
            )
        return POLL if call.sent else SERVICE_POLL

    def _poll_wait(self, w: _Wait, now: float, cancellable: bool = True) -> float | None:
        """None once reached; else the time to wait (raises Failed)."""
        unit = self.cell.units[w.unit]
        progress = self.cell.progress(unit, w.cmd, w.seq0, w.target)
        if progress == "reached":
            return None
        if progress:
            raise Failed(
                Reason.COMMAND_NOT_ALLOWED,
                f"{unit.name} went to {progress} instead of {state_name(w.target)}",
            )
        self._check(unit, now, cancellable)
        if not unit.online:
            raise Failed(
                Reason.UNIT_UNAVAILABLE,
                f"{unit.name} was lost while going to {state_name(w.target)}",
            )
        if now >= w.deadline:
            current = unit.status.state_current_name if unit.status is not None else "no status"
            raise Failed(
                Reason.UNIT_UNAVAILABLE,
                f"{unit.name} did not reach {state_name(w.target)} within {self.timeout:g} s (step_timeout; now {current})",
            )
        return min(w.deadline - now, POLL)


def answer_failure(unit: str, cmd: Cmd, a: Answer) -> Failed | None:
    if a.error is not None:
        return Failed(Reason.UNIT_UNAVAILABLE, a.error)
    if not a.accepted:
        return Failed(a.result, f"{unit} refused {cmd.name}: {a.message}")
    return None


class CommandRun(Run):
    """A cell command other than ABORT, unit by unit (see the module docstring)."""

    def __init__(self, cell: Cell, cmd: Cmd) -> None:
        super().__init__(cell, cmd.name)
        self.cmd = cmd
        self.order = list(cell.start_order if cmd in START_LIKE else cell.stop_order)
        self.index = 0
        self.started = 0.0
        self.call: _Call | None = None
        self.wait: _Wait | None = None
        self.text = ""  # what the step does when it ends well
        self.done: list[str] = []
        self.skipped: list[str] = []
        self.failed: list[tuple[int, str]] = []

    def refusals(self, now: float) -> Outcome | None:
        """All or nothing (STOP goes to every unit that can stop)."""
        if self.cmd is Cmd.STOP:
            return None
        refusals = self.cell.refusals(self.cmd, self.order, now)
        if not refusals:
            return None
        listed = "; ".join(text for _, text in refusals)
        return Outcome(False, refusals[0][0], f"{self.name} refused, no unit commanded: {listed}")

    def _where(self) -> str:
        return f"{self.order[self.index]} (step {self.index + 1}/{len(self.order)})"

    def _label(self) -> str:
        return f"{self.name} {self.index + 1}/{len(self.order)}: {self.order[self.index]}"

    def next(self, now: float, ready: Ready) -> tuple[list[UnitCall], float] | Outcome:
        out: list[UnitCall] = []
        while self.outcome is None:
            if self.index >= len(self.order):
                self.outcome = self._finish()
                break
            try:
                wait = self._advance(now, ready, out)
            except Failed as failure:
                self._fail(failure)
                continue
            if wait is not None:
                return out, wait
        assert self.outcome is not None
        return self.outcome

    def _advance(self, now: float, ready: Ready, out: list[UnitCall]) -> float | None:
        """One step of the current unit: the time to wait, or None when it moved on."""
        unit = self.cell.units[self.order[self.index]]
        target = unit.target(self.cmd)
        if self.call is None and self.wait is None:  # the step begins
            self.started = now
            deadline = now + self.timeout
            self._check(unit, now)
            self._online(unit, now)
            status = unit.status
            seq0 = unit.sequence()
            if target is not None and status.state_requested == target:
                if status.state_current == target:
                    self._next("skipped", f"{unit.name} (already {state_name(target)})")
                    return None
                self.step = f"{self._label()} on its way to {state_name(target)}"
                self.text = f"{unit.name} -> {state_name(target)} (was on its way)"
                self.wait = _Wait(unit.name, None, seq0, int(target), deadline)
            elif self.cmd is Cmd.STOP and Cmd.STOP not in unit.valid_commands():
                self._next("skipped", f"{unit.name} (cannot stop in {status.state_current_name})")
                return None
            else:
                self.step = f"{self._label()}: sending {self.name}"
                self.call = _Call(
                    unit.name, "command", {"command": int(self.cmd), "source": SOURCE}, deadline
                )
                self.seq0 = seq0
        if self.call is not None:
            a = self.call.answer
            if a is None:
                return self._poll_call(self.call, now, ready, out)
            failure = answer_failure(unit.name, self.cmd, a)
            if failure is not None:
                raise failure
            deadline = self.call.deadline
            self.call = None
            self.text = f"{unit.name} -> {state_name(a.state_requested)}"
            if a.state_current == a.state_requested:
                self._next("done", f"{self.text} ({now - self.started:.2f} s)")
                return None
            self.step = f"{self._label()}: waiting for {state_name(a.state_requested)}"
            self.wait = _Wait(unit.name, self.cmd, self.seq0, a.state_requested, deadline)
        assert self.wait is not None
        wait = self._poll_wait(self.wait, now)
        if wait is not None:
            return wait
        timed = self.wait.cmd is not None
        self.wait = None
        self._next("done", f"{self.text} ({now - self.started:.2f} s)" if timed else self.text)
        return None

    def _next(self, outcome: str, text: str) -> None:
        (self.done if outcome == "done" else self.skipped).append(text)
        self.index += 1
        self.call = self.wait = None

    def _fail(self, failure: Failed) -> None:
        where = self._where()
        if self.cmd is Cmd.STOP and failure.result != Reason.SUPERSEDED:
            self.failed.append((failure.result, f"{where}: {failure.message}"))
            self.index += 1
            self.call = self.wait = None
            return
        parts = [f"{self.name} stopped at {where}: {failure.message}"]
        if self.done:
            parts.append(f"done before: {', '.join(self.done)}")
        if self.skipped:
            parts.append(f"skipped: {', '.join(self.skipped)}")
        rest = self.order[self.index + 1 :]
        if rest:
            parts.append(f"not commanded: {', '.join(rest)}")
        self.outcome = Outcome(False, failure.result, "; ".join(parts))

    def _finish(self) -> Outcome:
        order = " > ".join(self.order)
        parts = [f"{self.name} done in order {order}"]
        if self.done:
            parts.append(", ".join(self.done))
        if self.skipped:
            parts.append(f"skipped: {', '.join(self.skipped)}")
        if self.failed:
            parts[0] = f"{self.name} not done on every unit (order {order})"
            parts.append(f"failed: {'; '.join(text for _, text in self.failed)}")
            return Outcome(False, self.failed[0][0], "; ".join(parts))
        return Outcome(True, Reason.ACCEPTED, "; ".join(parts))

    def answer(self, unit: str, service: str, answer: Answer) -> None:
        if self.call is not None and self.call.unit == unit and self.call.service == service:
            self.call.answer = answer


class AbortRun(Run):
    """ABORT to every unit at once; never cancelled."""

    def __init__(self, cell: Cell, now: float) -> None:
        super().__init__(cell, "ABORT")
        self.deadline = now + self.timeout
        self.target = next(
            (t for u in cell.units.values() if (t := u.target(Cmd.ABORT))), State.ABORTED
        )
        self.results: dict[str, str] = {}
        self.failed: list[tuple[int, str]] = []
        self.calls: dict[str, tuple[int, Answer | None]] = {}  # unit -> (seq0, answer)
        self.waits: dict[str, _Wait] = {}
        self.began = False

    def next(self, now: float, ready: Ready) -> tuple[list[UnitCall], float] | Outcome:
        out: list[UnitCall] = []
        if not self.began:
            self.began = True
            for unit in self.cell.units.values():
                status = unit.status
                if (
                    status is not None
                    and status.state_requested == unit.target(Cmd.ABORT)
                    and unit.online
                ):
                    self.results[unit.name] = f"{unit.name} already {status.state_current_name}"
                elif not ready(unit.name, "command"):  # lost units too: try whoever is there
                    self._failed(unit.name, Reason.UNIT_UNAVAILABLE, f"{unit.name} unreachable")
                else:
                    self.calls[unit.name] = (unit.sequence(), None)
                    out.append(
                        UnitCall(
                            unit.name, "command", {"command": int(Cmd.ABORT), "source": SOURCE}
                        )
                    )
            self.step = f"ABORT: waiting for {', '.join(self.calls) or 'nobody'}"
        for name, (seq0, a) in list(self.calls.items()):
            if a is None:
                if now >= self.deadline:
                    del self.calls[name]
                    self._failed(name, Reason.UNIT_UNAVAILABLE, f"{name} did not answer (timeout)")
                continue
            del self.calls[name]
            if a.error is not None:
                self._failed(name, Reason.UNIT_UNAVAILABLE, f"{name} did not answer ({a.error})")
            elif not a.accepted:
                self._failed(name, a.result, f"{name} refused ABORT: {a.message}")
            elif a.state_current != a.state_requested:
                self.waits[name] = _Wait(name, Cmd.ABORT, seq0, a.state_requested, self.deadline)
            else:
                self.results[name] = f"{name} -> {state_name(a.state_requested)}"
        for name, w in list(self.waits.items()):
            try:
                if self._poll_wait(w, now, cancellable=False) is None:
                    del self.waits[name]
                    self.results[name] = f"{name} -> {state_name(w.target)}"
            except Failed as failure:
                del self.waits[name]
                self._failed(name, failure.result, failure.message)
        if self.calls or self.waits:
            return out, min(POLL, max(0.0, self.deadline - now))
        listed = "; ".join(self.results[n] for n in self.cell.units if n in self.results)
        if self.failed:
            self.outcome = Outcome(
                False,
                self.failed[0][0],
                f"ABORT sent to every unit at once, not all aborted: {listed}",
            )
        else:
            self.outcome = Outcome(
                True, Reason.ACCEPTED, f"ABORT sent to every unit at once: {listed}"
            )
        return self.outcome

    def _failed(self, unit: str, result: int, text: str) -> None:
        self.results[unit] = text
        self.failed.append((result, text))

    def answer(self, unit: str, service: str, answer: Answer) -> None:
        if unit in self.calls and self.calls[unit][1] is None:
            self.calls[unit] = (self.calls[unit][0], answer)


@dataclass
class _Back:
    """A unit to change back to its mode of before."""

    unit: str
    deadline: float
    call: _Call | None = None


class ModeRun(Run):
    """A mode change of every unit, all or nothing (see the module docstring)."""

    def __init__(self, cell: Cell, mode: int, mode_name: str) -> None:
        wanted = mode_name or str(mode)
        super().__init__(cell, f"SET_MODE {wanted}")
        self.wanted = wanted
        self.mode, self.mode_name = mode, mode_name
        self.before = {
            n: u.status.unit_mode_current for n, u in cell.units.items() if u.status is not None
        }
        modes = set(self.before.values())
        self.old = next(iter(modes)) if len(modes) == 1 else 0
        self.number = mode
        self.order = list(cell.start_order)
        self.index = 0
        self.call: _Call | None = None
        self.lines: list[str] = []
        self.changed: list[str] = []
        self.refused: tuple[int, str] | None = None  # (result, message) once a unit refused
        self.back: list[_Back] = []
        self.notes: list[str] = []

    def refusals(self) -> Outcome | None:
        refusals, self.number = self.cell.mode_refusals(self.mode, self.mode_name)
        if not refusals:
            return None
        message = f"mode {self.wanted} refused, no unit changed: " + "; ".join(
            t for _, t in refusals
        )
        return Outcome(False, refusals[0][0], message, self.old)

    def next(self, now: float, ready: Ready) -> tuple[list[UnitCall], float] | Outcome:
        out: list[UnitCall] = []
        while self.outcome is None:
            if self.refused is not None:
                wait = self._change_back(now, ready, out)
                if wait is not None:
                    return out, wait
                continue
            if self.index >= len(self.order):
                message = f"mode {self.wanted} set on every unit: " + "; ".join(self.lines)
                self.outcome = Outcome(True, Reason.ACCEPTED, message, self.number)
                break
            name = self.order[self.index]
            if self.call is None:
                self.step = f"SET_MODE {self.wanted}: {name}"
                fields = {"mode": int(self.mode), "mode_name": self.mode_name, "source": SOURCE}
                self.call = _Call(name, "set_mode", fields, now + self.timeout)
            a = self.call.answer
            if a is None:
                try:
                    return out, self._poll_call(self.call, now, ready, out)
                except Failed as failure:
                    a = Answer(False, failure.result, failure.message)
            self.call = None
            if a.accepted:
                self.lines.append(f"{name}: accepted ({a.message})")
                if self.before.get(name) != self.number:
                    self.changed.append(name)
                self.index += 1
                continue
            text = a.error if a.error is not None else a.message
            result = Reason.UNIT_UNAVAILABLE if a.error is not None else a.result
            self.refused = (result, f"{name} refused: {text}")
            self.back = [_Back(n, now + self.timeout) for n in self.changed]
        assert self.outcome is not None
        return self.outcome

    def _change_back(self, now: float, ready: Ready, out: list[UnitCall]) -> float | None:
        """Put the units changed back, each once its change is done: the time to wait, or None
        when every one is done (the outcome is set)."""
        while self.back:
            b = self.back[0]
            unit = self.cell.units[b.unit]
            if b.call is None:
                status = unit.status
                if (
                    status is not None
                    and (
                        status.unit_mode_change_in_process
                        or status.unit_mode_current != self.number
                    )
                    and now < b.deadline
                ):
                    return min(POLL, b.deadline - now)
                b.call = _Call(
                    b.unit,
                    "set_mode",
                    {"mode": self.before[b.unit], "mode_name": "", "source": SOURCE},
                    b.deadline,
                )
            a = b.call.answer
            if a is None:
                try:
                    return self._poll_call(b.call, now, ready, out, cancellable=False)
                except Failed as failure:
                    self.notes.append(f"{b.unit} (not back: {failure.message})")
                    self.back.pop(0)
                    continue
            if a.error is not None:
                self.notes.append(f"{b.unit} (not back: {a.error})")
            else:
                self.notes.append(f"{b.unit} ({'back' if a.accepted else 'refused: ' + a.message})")
            self.back.pop(0)
        assert self.refused is not None
        result, text = self.refused
        undone = ", ".join(self.notes)
        message = (
            f"mode {self.wanted} not set: {text}; "
            f"{'changed back: ' + undone if self.changed else 'no unit changed'}"
        )
        self.outcome = Outcome(False, result, message, self.old)
        return None

    def answer(self, unit: str, service: str, answer: Answer) -> None:
        if self.call is not None and self.call.unit == unit:
            self.call.answer = answer
        for b in self.back:
            if b.call is not None and b.unit == unit and b.call.answer is None and b.call.sent:
                b.call.answer = answer
                break


@dataclass
class Runs:
    """The runs in progress: one sequence (command or mode change) at a time, ABORTs besides."""

    active: dict[int, Run] = field(default_factory=dict)
    sequence: int | None = None  #: id of the run holding the sequence slot
    next_id: int = 1

    def add(self, run: Run, exclusive: bool) -> int | None:
        """Register ``run``; None when ``exclusive`` and another sequence runs."""
        if exclusive and self.sequence is not None:
            return None
        run_id = self.next_id
        self.next_id += 1
        self.active[run_id] = run
        if exclusive:
            self.sequence = run_id
        return run_id

    def remove(self, run_id: int) -> None:
        self.active.pop(run_id, None)
        if self.sequence == run_id:
            self.sequence = None

    def cancel_all(self, by: str) -> None:
        """Cancel what runs; an ABORT never, a STOP not by another STOP (that one joins it)."""
        for run in self.active.values():
            if not isinstance(run, AbortRun) and not (by == "STOP" and _is_stop(run)):
                run.cancel(by)

    def running_stop(self) -> str | None:
        """The step of the cell STOP in progress (another STOP joins it), None when none runs."""
        run = self.active.get(self.sequence) if self.sequence is not None else None
        return run.step if run is not None and _is_stop(run) else None

    def busy_text(self) -> str:
        return next(reversed([r.step for r in self.active.values()]), "a sequence")

    @property
    def step(self) -> str:
        return next(reversed([r.step for r in self.active.values()]), "")


def _is_stop(run: Run) -> bool:
    return isinstance(run, CommandRun) and run.cmd is Cmd.STOP
