"""Issue 26: ``ctx.finish`` and cancellation hold under any sequence of statuses.

The EM's status-following core (:class:`packml_ros2.core.em_hooks.HookRunner`) runs on an event
loop whose clock is virtual (time jumps to the next timer: a 3 s move costs nothing), following a
real engine :class:`~packml_ros2.core.Unit` with a second EM ("other") that reports at once and
raises alarms. Hypothesis draws moves of random length and random inputs (commands, the other EM's
alarms, alarm resets, mode changes, repeated Stop/Abort) at random times; the invariants:

- no hook starts while a move wrapped in ``ctx.finish`` runs (Abort cancels one at once, and its
  cancellation has ended before ``on_aborting`` starts);
- a finished move is cut only by Abort;
- State Complete is reported once per (state, sequence), only while the unit is in it, and none is
  lost: once the inputs stop and the moves have had their time, the unit waits for no report.
"""

from __future__ import annotations

import asyncio
import selectors
from dataclasses import dataclass, field
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from packml_ros2.core import Cmd, State, Unit
from packml_ros2.core.em_hooks import HookRunner, StateContext, StatusView
from packml_ros2.core.numbers import ACTING

from .helpers import cell_unit

T0 = 10_000.0
ROBOT, OTHER = "robot", "other"
ALARMS = {201: "stop", 202: "abort", 203: "hold", 204: "info"}
CONFIG = cell_unit(
    {
        "equipment_modules": {ROBOT: {}, OTHER: {}},
        "em_lease": 1e9,
        "admin_period": 1e9,
        "modes": {"maintenance": {"mode_change_states": ["Stopped", "Idle", "Aborted", "Held"]}},
        "alarms": [
            {"id": 201, "message": "guard open", "category": 3},
            {"id": 202, "message": "e-stop", "category": 0},
            {"id": 203, "message": "jam", "category": 7, "reaction": "hold"},
            {"id": 204, "message": "info", "category": 6},
        ],
    }
)


class _VirtualSelector(selectors.DefaultSelector):
    """Polls the real selector (the loop's self-pipe); where the loop would block, the virtual
    clock jumps by the timeout instead."""

    def __init__(self, loop: VirtualLoop) -> None:
        super().__init__()
        self._vloop = loop

    def select(self, timeout: float | None = None) -> list[Any]:
        ready = super().select(0)
        if not ready:
            assert timeout is not None, "the loop would wait forever"
            self._vloop.now += timeout
        return ready


class VirtualLoop(asyncio.SelectorEventLoop):
    """An event loop on a virtual clock."""

    def __init__(self) -> None:
        self.now = 0.0
        super().__init__(_VirtualSelector(self))

    def time(self) -> float:
        return self.now


@dataclass
class Trace:
    """What happened, checked as it happens."""

    unit: Unit
    moves_running: int = 0
    hooks: list[tuple[State, int]] = field(default_factory=list)
    reports: set[tuple[int, int]] = field(default_factory=set)
    cut_moves: int = 0
    #: broken invariants, noted where they happen (an assert inside a hook or a task would only
    #: end that task), checked at the end
    broken: list[str] = field(default_factory=list)

    def expect(self, ok: bool, what: str) -> None:
        if not ok:
            self.broken.append(what)

    def check_report(self, state: int, sequence: int) -> None:
        key = (int(state), sequence)
        self.expect(key not in self.reports, f"State Complete {key} doubled")
        now = (int(self.unit.state), self.unit.sequence)
        self.expect(key == now, f"State Complete {key} while the unit is in {now}")
        self.reports.add(key)


def view_of(unit: Unit) -> StatusView:
    s = unit.status()
    mine = next(((e.active, e.state_complete) for e in s.equipment if e.name == ROBOT), None)
    return StatusView(s.state_current, s.sequence, s.unit_mode_current, s.unit_mode_requested,
                      s.unit_mode_change_in_process, mine)  # fmt: skip


class Harness:
    """A unit, the other EM, and the robot EM's runner with hooks made of moves."""

    def __init__(self, loop: VirtualLoop, moves: list[float], cycles: int) -> None:
        self.loop = loop
        self.unit = Unit(CONFIG, lambda: T0 + loop.time())
        self.trace = Trace(self.unit)
        self.moves = moves
        self.cycles = cycles  # Execute returns after this many moves (0: runs until left)
        self.draws = 0
        self.runner = HookRunner(
            ROBOT, loop, self.hook_for, lambda: self.hook, self.report, self.failed
        )
        for em in (ROBOT, OTHER):
            assert self.unit.em_seen(em).accepted
        self.publish()

    def duration(self) -> float:
        self.draws += 1
        return self.moves[self.draws % len(self.moves)]

    # -- the unit side ---------------------------------------------------------------------------
    def publish(self) -> None:
        """After every input: the status goes out (in order, as the latched topic delivers it);
        the other EM reports at once."""
        self.unit.drain()
        view = view_of(self.unit)
        self.loop.call_soon(self.runner.on_status, view)
        other = next(e for e in self.unit.status().equipment if e.name == OTHER)
        if (self.unit.state in ACTING or view.mode_changing) and not other.state_complete:
            self.loop.call_soon(self.other_complete, view.key)

    def other_complete(self, key: tuple[int, int]) -> None:
        if (self.unit.state, self.unit.sequence) == key:
            self.unit.em_complete(OTHER, *key)
            self.publish()

    def apply(self, action: tuple[Any, ...]) -> None:
        kind, arg = action
        if kind == "cmd" and arg:
            self.unit.command(arg)
        elif kind == "alarm":
            self.unit.em_alarm(OTHER, arg, 0, True)
        elif kind == "reset_alarms":
            self.unit.em_alarm(OTHER, arg, 0, False)
            self.unit.reset_alarms()
        elif kind == "mode":
            self.unit.set_mode(arg)
        self.publish()

    # -- the robot EM --------------------------------------------------------------------------------
    def report(self, state: State, sequence: int) -> None:
        self.trace.check_report(state, sequence)
        self.unit.em_complete(ROBOT, int(state), sequence)
        self.publish()

    def failed(self, hook: Any, ctx: StateContext, exc: Exception) -> None:
        self.trace.broken.append(f"hook failed in {ctx.state.name}: {exc!r}")

    def hook_for(self, state: State) -> Any:
        return self.execute if state is State.EXECUTE else self.hook

    def started(self, ctx: StateContext) -> None:
        self.trace.expect(self.trace.moves_running == 0, f"{ctx.state.name} started during a move")
        self.trace.hooks.append((ctx.state, ctx.sequence))

    async def move(self, ctx: StateContext) -> None:
        self.trace.moves_running += 1
        try:
            await asyncio.sleep(self.duration())
        except asyncio.CancelledError:
            cut_in = self.unit.state
            self.trace.expect(cut_in is State.ABORTING, f"a finished move cut in {cut_in.name}")
            self.trace.cut_moves += 1
            raise
        finally:
            self.trace.moves_running -= 1

    async def hook(self, ctx: StateContext) -> None:
        self.started(ctx)
        await ctx.finish(self.move(ctx))

    async def execute(self, ctx: StateContext) -> None:
        self.started(ctx)
        done = 0
        while not self.cycles or done < self.cycles:
            await ctx.finish(self.move(ctx))
            done += 1


ACTIONS = st.one_of(
    st.tuples(st.just("cmd"), st.sampled_from(list(Cmd)[1:])),
    st.tuples(st.just("cmd"), st.sampled_from([Cmd.STOP, Cmd.ABORT, Cmd.HOLD])),
    st.tuples(st.just("alarm"), st.sampled_from(sorted(ALARMS))),
    st.tuples(st.just("reset_alarms"), st.sampled_from(sorted(ALARMS))),
    st.tuples(st.just("mode"), st.sampled_from([1, 2])),
)
STEPS = st.lists(st.tuples(st.floats(0.0, 3.0), ACTIONS), max_size=25)


def play(moves: list[float], cycles: int, steps: list[tuple[float, tuple[Any, ...]]]) -> Trace:
    loop = VirtualLoop()
    try:
        h = Harness(loop, moves, cycles)
        # Reset, Start (each after the acting state's move): most inputs then meet a cell in motion
        step = 1.2 * max(moves)
        prelude = [(0.0, ("cmd", Cmd.RESET)), (step, ("cmd", Cmd.START)), (step, ("cmd", 0))]
        at = 0.0
        for delay, action in [*prelude, *steps]:
            at += delay
            loop.call_at(at, h.apply, action)
        unit = h.unit

        def waiting() -> bool:
            """The unit waits for a report (an Execute that never returns waits for none)."""
            endless = unit.state is State.EXECUTE and not cycles
            return (unit.state in ACTING and not endless) or unit.mode_change_in_process

        async def settle() -> None:
            """All inputs applied, then until the unit waits for nothing or the moves have had
            far more than their time."""
            await asyncio.sleep(at - loop.time())
            limit = loop.time() + 4.0 * max(moves) * (cycles + 2) + 1.0
            while waiting() and loop.time() < limit:
                await asyncio.sleep(0.25)

        loop.run_until_complete(settle())
        assert not waiting(), f"the unit still waits in {unit.state.name}: a report was lost"
        assert not h.trace.broken, h.trace.broken
        return h.trace
    finally:
        for task in asyncio.all_tasks(loop):
            task.cancel()
        loop.run_until_complete(asyncio.sleep(0))
        loop.close()


@pytest.mark.timeout(900)  # 1000 examples: about 40 s on an idle 2-core machine
@settings(max_examples=1000, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    moves=st.lists(st.floats(0.1, 3.0), min_size=1, max_size=5),
    cycles=st.integers(0, 3),
    steps=STEPS,
)
def test_no_hook_starts_during_a_finished_move_and_no_report_is_lost_or_doubled(
    moves: list[float], cycles: int, steps: list[tuple[float, tuple[Any, ...]]]
) -> None:
    play(moves, cycles, steps)


def test_the_reported_sequence_stop_during_a_move_then_another_ems_alarm() -> None:
    """Stop during a 2 s move, another EM's Stop-category alarm 0.5 s later: the move ends, then
    on_stopping starts (before the fix the alarm's status cancelled the hook again and cut the
    move)."""
    trace = play([2.0], 0, [(0.5, ("cmd", Cmd.STOP)), (0.5, ("alarm", 201))])
    states = [s for s, _ in trace.hooks]
    assert states[-1] is State.STOPPING and trace.cut_moves == 0


def test_abort_cuts_a_finished_move_at_once() -> None:
    """Stop during a move, then Abort while it finishes: the move is cancelled (E-stop path)."""
    trace = play([5.0], 0, [(0.5, ("cmd", Cmd.STOP)), (0.5, ("cmd", Cmd.ABORT))])
    assert trace.cut_moves == 1
    assert [s for s, _ in trace.hooks][-1] is State.ABORTING
