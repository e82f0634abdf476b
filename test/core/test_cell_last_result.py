"""Issue 24 item 9: the cell's detail says the outcome of the last cell command ("last: START
failed (…)") only while it is news: once the cell's state changed (the units were started one by
one, say), the overview no longer shows a failed START beside a running cell."""

from __future__ import annotations

from packml_ros2.core import Cmd, State
from test.core.line_sim import SimEm, SimLine
from test.core.test_line_scenarios import D, cell_doc, started


def test_a_failed_start_is_not_shown_once_the_cell_runs() -> None:
    sim = SimLine(cell_doc(), [SimEm("filler", "infeed", dict(D), 1.0, 10),
                               SimEm("packer", "loader", dict(D), 2.0)])  # fmt: skip
    sim.at(1, lambda: sim.cell_command(Cmd.RESET))
    sim.run_until(3)
    assert sim.line.view().state_current == State.IDLE
    sim.line.last_result = "START failed (1.2 s)"  # as the coordinator node records it
    assert "last: START failed (1.2 s)" in sim.line.view().detail  # news while nothing changed
    sim.run_until(3.5)
    assert "last: START failed (1.2 s)" in sim.line.view().detail
    # the operator starts the units one by one (at their panels): the cell runs
    sim.at(4, lambda: sim.command("packer", Cmd.START))
    sim.at(4, lambda: sim.command("filler", Cmd.START))
    sim.run_until(10)
    view = sim.line.view()
    assert view.state_current == State.EXECUTE
    assert "START failed" not in view.detail, view.detail


def test_a_result_given_in_the_state_it_led_to_stays() -> None:
    sim = started(cell_doc())
    sim.run_until(10)
    sim.line.last_result = "START done (0.6 s)"
    sim.run_until(12)
    assert "last: START done (0.6 s)" in sim.line.view().detail
    sim.cell_command(Cmd.STOP)
    sim.run_until(20)
    assert sim.line.view().state_current == State.STOPPED
    assert "START done" not in sim.line.view().detail
