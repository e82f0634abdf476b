"""Issue 14 (b): edge cases a plant hits, engine side. Each test failed before its fix.

Node-side cases (an EM switched active mid-state, the configured lease, a stray heartbeat, two
units on one store, the coordinator) are in test/ros."""

from __future__ import annotations

from packml_ros2.core import Mode, Reason, Unit

from .helpers import FakeClock, cell_unit


# -- 4: ModeCurrentTime of a mode left is 0 (PACKML.md 6) -----------------------------------------------
def test_mode_current_time_is_zero_after_leaving_the_mode() -> None:
    clock = FakeClock()
    unit = Unit(cell_unit({}), clock)
    clock.advance(7.0)
    assert unit.set_mode("maintenance").accepted and unit.mode == Mode.MAINTENANCE
    clock.advance(3.0)
    unit.advance()
    times = unit.admin().times
    assert times.mode_current[Mode.PRODUCTION] == 0
    assert times.mode_cumulative[Mode.PRODUCTION] == 7
    assert times.mode_current[Mode.MAINTENANCE] == 3
    assert unit.set_mode("production").accepted
    clock.advance(2.0)
    unit.advance()
    times = unit.admin().times
    assert times.mode_current[Mode.MAINTENANCE] == 0
    assert times.mode_cumulative[Mode.MAINTENANCE] == 3
    assert times.mode_current[Mode.PRODUCTION] == 2  # since it was entered again


# -- 5: counters only go up ------------------------------------------------------------------------------------
def test_negative_count_increment_is_refused() -> None:
    clock = FakeClock()
    unit = Unit(cell_unit({"counters": {"processed": [{"id": 1}]}}), clock)
    assert unit.em_count("em", "processed", 0, 5).accepted
    refused = unit.em_count("em", "processed", 0, -3)
    assert not refused.accepted and refused.reason is Reason.INVALID_ARGUMENT
    assert "-3" in refused.message
    counter = unit.admin().prod_processed_count[0]
    assert (counter.count, counter.acc_count) == (5, 5)
