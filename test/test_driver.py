"""The one mapping of EM reports to engine inputs (packml_ros2.driver), without DDS."""

from __future__ import annotations

from packml_interfaces.msg import EmReport

from packml_ros2.core import Cmd, Unit
from packml_ros2.core.liveliness import Liveliness
from packml_ros2.driver import FrozenClock, UnitDriver
from test.core.helpers import cell_unit


def test_reports_of_made_up_ems_mid_production_keep_nothing_and_say_little() -> None:
    now = [100.0]
    clock = FrozenClock(lambda: now[0])
    unit = Unit(cell_unit({"counters": {"processed": [{"id": 1}]}}), clock)
    emitted: list[tuple[str, object]] = []
    driver = UnitDriver(unit, clock, lambda topic, msg: emitted.append((topic, msg)))
    live = Liveliness(2.0)
    driver.call(now[0], unit.command, Cmd.RESET)
    driver.call(now[0], unit.command, Cmd.START)
    for i in range(1000):  # a flood of names, each with a count it must not get in
        report = EmReport(em=f"ghost{i}", kind=EmReport.KIND_COUNT, counter=1, increment=5)
        driver.report(now[0], report, live)
    assert not live.last_seen and not live.alive and not live.announced
    assert unit.admin().prod_processed_count[0].count == 0
    assert len(unit.equipment) == 0 and unit.state.name == "EXECUTE"
    warnings = [m for topic, m in emitted if topic == "log" and "not registered" in str(m)]
    assert len(warnings) == 64  # each name said once, up to 64 names


def test_the_next_lease_expiry_is_when_the_longest_silent_em_runs_out() -> None:
    """The unit node arms one timer for it instead of polling the leases."""
    live = Liveliness(2.0)
    assert live.next_expiry() == float("inf")  # nobody alive: nothing to wake up for
    live.seen("a", 10.0)
    live.seen("b", 11.0)
    assert live.next_expiry() == 12.0
    assert live.expired(12.0) == []  # strict: lost only after the lease
    assert live.expired(12.001) == [("a", 2.0)]
    assert live.next_expiry() == 13.0
    live.left("b")
    assert live.next_expiry() == float("inf")
