"""Issue 14 (b): edge cases a plant hits, engine side. Each test failed before its fix.

Node-side cases (an EM switched active mid-state, the configured lease, a stray heartbeat, two
units on one store, the coordinator) are in test/ros."""

from __future__ import annotations

from packml_ros2.core import Cmd as C
from packml_ros2.core import Mode, Reason, State, Unit

from .helpers import FakeClock, cell_unit

S = State


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


# -- 3: a stray report never registers an EM mid-production --------------------------------------------
def test_an_unknown_ems_report_registers_it_only_at_rest() -> None:
    unit = Unit(cell_unit({}), FakeClock())  # allow_registration: true (the default)
    assert unit.command(C.RESET).accepted and unit.command(C.START).accepted
    assert unit.state is S.EXECUTE and unit.mode == Mode.PRODUCTION
    for _ in range(3):  # its heartbeats keep coming: refused each time, said once in the log
        refused = unit.em_seen("stray", report=True)
        assert not refused.accepted and refused.reason is Reason.EM_UNKNOWN, refused
    assert "only at rest" in refused.message and "EXECUTE" in refused.message
    logs = [text for kind, (level, text) in _logs(unit)]
    assert sum("stray" in text for text in logs) == 1, logs
    assert unit.equipment.get("stray") is None and unit.state is S.EXECUTE
    assert unit.command(C.STOP).accepted and unit.state is S.STOPPED  # at rest: it registers
    assert unit.em_seen("stray", report=True).accepted
    assert unit.equipment.get("stray") is not None


def _logs(unit: Unit) -> list[tuple[str, tuple[str, str]]]:
    return [(kind, item) for kind, item in unit.drain() if kind == "log"]
