"""Issue 25 item 6 in the engine: a step of the wall clock (NTP) is an input, ``clock_step``.

The engine runs on the wall clock (its timestamps are wall time). When that clock steps, the unit
node tells the engine, and its timeline moves with the clock: every deadline (a state's timeout,
the mode change's, the changeover's, the periodic admin) and the start of every running time
keep the seconds they had left or had run. Without the input a step forward times out the
state at once and counts the step in the times; a step back silences the periodic admin."""

from __future__ import annotations

from typing import Any

import pytest

from packml_ros2.core import Cmd as C
from packml_ros2.core import State, Unit, inputlog
from packml_ros2.core.times import NUM_STATES

from .helpers import FakeClock, cell_unit, transitions

S = State
DOC: dict[str, Any] = {
    "equipment_modules": {"em1": {}},
    "timeouts": {"Starting": 5},
    "admin_period": 2.0,
}


def starting(doc: dict[str, Any] = DOC) -> tuple[Unit, FakeClock]:
    clock = FakeClock(1_000.0)
    unit = Unit(cell_unit(doc), clock)
    assert unit.em_seen("em1").accepted
    assert unit.command(C.RESET).accepted
    assert unit.em_complete("em1", unit.state, unit.sequence).accepted
    assert unit.command(C.START).accepted
    assert unit.state is S.STARTING
    unit.drain()
    return unit, clock


def step(unit: Unit, clock: FakeClock, offset: float) -> None:
    clock.advance(offset)
    assert unit.clock_step(offset).accepted


@pytest.mark.parametrize("offset", [60.0, 3600.0, -60.0, -3600.0])
def test_a_step_keeps_a_states_timeout_on_elapsed_time(offset: float) -> None:
    unit, clock = starting()
    clock.advance(3.0)
    unit.advance()
    step(unit, clock, offset)
    clock.advance(1.99)  # 4.99 s of the 5 s elapsed
    unit.advance()
    assert unit.state is S.STARTING and not unit.alarms.current
    clock.advance(0.01)
    unit.advance()
    assert unit.state is S.STOPPING, "the timeout fires after 5 s elapsed"


def test_without_the_input_a_step_forward_times_the_state_out_at_once() -> None:
    """What the input prevents (the test above fails this way when clock_step shifts nothing)."""
    unit, clock = starting()
    clock.advance(60.0)
    unit.advance()
    assert unit.state is S.STOPPING


def test_times_count_elapsed_seconds_and_timestamps_follow_the_new_clock() -> None:
    unit, clock = starting()
    assert unit.em_complete("em1", unit.state, unit.sequence).accepted
    assert unit.state is S.EXECUTE
    clock.advance(10.0)
    step(unit, clock, 3600.0)
    clock.advance(10.0)
    step(unit, clock, -7200.0)
    clock.advance(10.0)
    unit.advance()
    admin = unit.admin()
    assert admin.times.state_current[unit.mode * NUM_STATES + S.EXECUTE] == pytest.approx(30.0)
    assert admin.times.acc_time_since_reset == pytest.approx(30.0)  # (all of it since the start)
    assert unit.command(C.STOP).accepted
    stop = transitions(unit)[-1]
    assert stop.time == pytest.approx(clock.t), "transitions are stamped with the new wall time"
    assert stop.time < 1_000.0  # (the clock went back an hour)


def test_a_step_back_does_not_silence_the_periodic_admin() -> None:
    unit, clock = starting()
    step(unit, clock, -60.0)
    admins = 0
    for _ in range(5):
        clock.advance(1.0)
        unit.advance()
        admins += sum(1 for kind, _ in unit.drain() if kind == "admin")
    assert admins >= 2, "an admin every 2 s goes on"


def test_a_step_is_an_event_of_the_admin_history_and_replays() -> None:
    clock = FakeClock(1_000.0)
    unit = Unit(cell_unit(DOC), clock)
    log: list[tuple[float, str, dict[str, Any]]] = []
    unit.on_input = lambda t, name, fields: log.append((t, name, fields))
    assert unit.em_seen("em1").accepted
    assert unit.command(C.RESET).accepted
    assert unit.em_complete("em1", unit.state, unit.sequence).accepted
    assert unit.command(C.START).accepted
    clock.advance(2.0)
    step(unit, clock, -60.0)
    clock.advance(2.5)
    unit.advance()
    assert unit.state is S.STARTING
    clock.advance(1.0)
    unit.advance()
    assert unit.state is S.STOPPING
    history = [e.message for e in unit.alarms.history]
    assert any("wall clock stepped -60.000 s" in m for m in history), history
    assert [name for _, name, _ in log].count(inputlog.CLOCK_STEP.name) == 1
    again_clock = FakeClock(1_000.0)
    again = Unit(cell_unit(DOC), again_clock)
    for t, name, fields in log:
        again_clock.t = t
        inputlog.apply(again, name, fields)
    again_clock.t = clock.t
    again.advance()
    assert transitions(again) == transitions(unit)


def test_a_step_that_is_not_a_number_is_refused_and_changes_nothing() -> None:
    unit, _ = starting()
    due = unit.next_deadline()
    answer = unit.clock_step(float("nan"))
    assert not answer.accepted
    assert unit.next_deadline() == due
