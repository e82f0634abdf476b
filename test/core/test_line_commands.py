"""Cell commands while a sequence runs, decided in the core (issue 28 item 4): ABORT cancels
and begins at once; STOP cancels the sequence and begins when it has ended, joins a STOP in
progress, and gives up as busy after ``step_timeout`` + STOP_GIVE_UP; any other command and a
mode change are refused as busy (a flag, not a word in the message). Real engines on the
simulated line (test/core/line_sim.py)."""

from __future__ import annotations

from typing import Any

from packml_ros2.core import Cmd, Reason, State
from packml_ros2.core.line.line import STOP_GIVE_UP
from packml_ros2.core.line.sequence import Outcome, StopWaits
from test.core.line_sim import SimEm, SimLine

SLOW = {State.RESETTING: 1.0, State.STARTING: 4.0, State.STOPPING: 1.0, State.ABORTING: 0.5,
        State.CLEARING: 0.5}  # fmt: skip


def line(step_timeout: float = 15.0) -> SimLine:
    doc: dict[str, Any] = {
        "cell": "sim",
        "defaults": {"remote_commands_enabled": True, "persistence": False},
        "units": {"a": {"equipment_modules": {"em": {}}}, "b": {"equipment_modules": {"em": {}}}},
        "coordinator": {"start_order": ["a", "b"], "step_timeout": step_timeout},
        "line": {"store": False},
    }
    sim = SimLine(doc, [SimEm("a", "em", dict(SLOW)), SimEm("b", "em", dict(SLOW))])
    sim.at(1, lambda: sim.cell_command(Cmd.RESET))
    sim.run_until(4)
    assert {u.state for u in sim.units.values()} == {State.IDLE}
    return sim


def test_a_stop_during_a_start_cancels_it_and_stops_every_unit() -> None:
    sim = line()
    start = sim.cell_command(Cmd.START)
    sim.run_until(5)  # a is Starting (4 s), b waits its turn
    assert sim.units["a"].state == State.STARTING and start == []
    stop = sim.cell_command(Cmd.STOP)
    assert start and not start[0].accepted, start  # the START ended, cancelled by the STOP
    sim.run_until(12)
    assert stop and stop[0].accepted, stop
    assert {u.state for u in sim.units.values()} == {State.STOPPED}


def test_a_second_stop_joins_the_stop_in_progress() -> None:
    sim = line()
    first = sim.cell_command(Cmd.STOP)
    assert first == []  # Stopping takes 1 s
    second = sim.line.begin_command(Cmd.STOP, "operator")
    assert isinstance(second, Outcome) and second.accepted, second
    assert "joined the STOP in progress" in second.message


def test_other_commands_and_mode_changes_are_refused_as_busy_and_change_nothing() -> None:
    sim = line()
    sim.cell_command(Cmd.START)
    sim.run_until(5)
    for cmd in (Cmd.RESET, Cmd.HOLD, Cmd.START):
        refused = sim.line.begin_command(cmd, "operator")
        assert isinstance(refused, Outcome) and refused.busy and not refused.accepted, refused
        assert refused.result == Reason.COMMAND_NOT_ALLOWED
    mode = sim.line.begin_mode(3, "")
    assert isinstance(mode, Outcome) and mode.busy and not mode.accepted
    # a refusal of another kind is not busy
    sim.run_until(14)
    assert {u.state for u in sim.units.values()} == {State.EXECUTE}
    other = sim.line.begin_mode(99, "")
    assert isinstance(other, Outcome) and not other.accepted and not other.busy, other


def test_a_stop_gives_up_as_busy_when_the_sequence_does_not_end() -> None:
    sim = line(step_timeout=2.0)
    sim.cell_command(Cmd.START)
    sim.run_until(5)
    waits = sim.line.begin_command(Cmd.STOP, "operator")
    assert isinstance(waits, StopWaits)  # the START was asked to end (it did not, yet)
    # asked again past step_timeout + STOP_GIVE_UP since it was first asked: busy
    sim.t += 2.0 + STOP_GIVE_UP + 0.1
    late = sim.line.begin_command(Cmd.STOP, "operator", waits.since)
    assert isinstance(late, Outcome) and late.busy and not late.accepted, late


def test_abort_during_a_start_begins_at_once() -> None:
    sim = line()
    sim.cell_command(Cmd.START)
    sim.run_until(5)
    begun = sim.line.begin_command(Cmd.ABORT, "operator")
    assert not isinstance(begun, (Outcome, StopWaits)), begun


def test_while_a_sequence_runs_the_cell_lists_only_what_interrupts_it() -> None:
    sim = line()
    assert Cmd.START in sim.line.view().commands_valid
    sim.cell_command(Cmd.START)
    sim.run_until(5)
    assert set(sim.line.view().commands_valid) <= {Cmd.STOP, Cmd.ABORT}
    assert Cmd.STOP in sim.line.view().commands_valid
    sim.run_until(14)  # the START has ended
    assert Cmd.STOP in sim.line.view().commands_valid and Cmd.HOLD in sim.line.view().commands_valid
