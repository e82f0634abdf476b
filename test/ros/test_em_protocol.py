"""Issue 26 item 5: the EM protocol (docs/em-protocol.md) is enough to write an EM without this
package. An EM in plain rclpy (test/ros/plain_em.py, its own process) and one on the base class
pass the same checks of the EM test harness (packml_ros2.testing.em_harness), against a real
unit node over DDS; and the checks fail an EM that breaks the protocol."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from packml_ros2.equipment_module import EquipmentModule, StateContext
from packml_ros2.testing.em_harness import LIFECYCLE, EmTestUnit

PLAIN_EM = Path(__file__).with_name("plain_em.py")


def start_plain(processes, unit: EmTestUnit, em: str = "plain", *args: str):  # type: ignore[no-untyped-def]
    return processes.start(f"plain_{em}", str(PLAIN_EM), unit.cell, unit.unit, em, *args)


def test_a_plain_rclpy_em_joins_a_unit_and_passes_the_checks(ros, processes, tmp_path) -> None:
    unit = EmTestUnit(ros, tmp_path, {"plain": {}})
    start_plain(processes, unit)
    seen = unit.check_lifecycle("plain")
    assert [c.state for c in seen] == [acting for _, acting, _ in LIFECYCLE]
    assert all(c.reports >= 1 for c in seen)
    unit.to_execute()
    assert unit.wait_count("processed", 2) >= 2


def test_a_base_class_em_passes_the_same_checks(ros, tmp_path) -> None:
    class Robot(EquipmentModule):
        async def on_starting(self, ctx: StateContext) -> None:
            await asyncio.sleep(0.1)

        async def execute(self, ctx: StateContext) -> None:
            while True:
                await ctx.finish(asyncio.sleep(0.2))
                self.count("processed")

    unit = EmTestUnit(ros, tmp_path, {"robot": {}})
    ros.add(Robot("robot", unit.unit, unit.cell, context=ros.context))
    unit.check_lifecycle("robot")
    unit.to_execute()
    unit.wait_count("processed", 2)


def test_the_plain_em_waits_out_its_work_and_says_goodbye(ros, processes, tmp_path) -> None:
    """The unit waits in an acting state until the EM reports; a goodbye makes it lost (its
    configured reaction: stop) after em_leave_grace, with the EM-lost alarm."""
    unit = EmTestUnit(ros, tmp_path, {"plain": {"lost_reaction": "stop"}})
    proc = start_plain(processes, unit, "plain", "1.5")  # every acting state takes 1.5 s
    unit.wait_online("plain")
    unit.command_to("reset", "RESETTING")
    unit.assert_waits_in("RESETTING", 0.5)
    unit.wait_entered("IDLE", timeout=10)
    unit.command_to("start", "STARTING")
    unit.wait_entered("EXECUTE", timeout=10)
    assert proc.stop() == 0
    assert "EM plain left unit u (SIGINT)" in proc.output()
    unit.wait_offline("plain")
    alarm = unit.wait_alarm(unit.node.unit.config.system_alarms.em_lost)
    assert "plain" in alarm.message
    unit.wait_state("STOPPED")


def test_the_checks_fail_an_em_that_reports_the_wrong_sequence(ros, tmp_path) -> None:
    """A harness whose checks cannot fail proves nothing: an EM that reports State Complete for
    an old sequence leaves the unit waiting, and check_lifecycle says so."""

    class Stale(EquipmentModule):
        def report_complete(self, state: int | None = None, sequence: int | None = None) -> None:
            super().report_complete(state, (self.sequence if sequence is None else sequence) - 1)

    unit = EmTestUnit(ros, tmp_path, {"stale": {}})
    ros.add(Stale("stale", unit.unit, unit.cell, context=ros.context))
    with pytest.raises(TimeoutError, match="IDLE"):
        unit.check_lifecycle("stale", timeout=2.0)
