"""Issue 25 item 14: a heartbeat queued before the lease wake-up counts.

Under 12 000 fuzzed requests a unit declared an EM lost once: its executor ran the lease wake-up
before the EM's heartbeats that had arrived in time and waited in its queue. Here the unit's own
executor is held (as a loaded one is) while the EM, in the test's executor, beats on; once the
unit has processed no heartbeat for longer than its lease, its wake-up runs first. It judges the
lease only after what waits in the executor's queue: the EM stays online (before: "no report for
1 s", the EM lost). The wake-up reads no topic itself (a read outside the executor left rclpy's
EventsExecutor serving those topics no more, now and then: a unit deaf to its EMs)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import pytest
from rclpy.executors import SingleThreadedExecutor

from packml_ros2.equipment_module import EquipmentModule
from packml_ros2.unit_node import UnitNode
from test.ros.cells import unit_config_of, write_cell

pytestmark = pytest.mark.ros
LEASE = 1.0


def test_a_heartbeat_waiting_in_the_queue_renews_the_lease(ros: Any, tmp_path: Path) -> None:
    cell_file, cell = write_cell(tmp_path, {"u": {"equipment_modules": {"robot": {}}, "em_lease": LEASE}})  # fmt: skip
    unit = UnitNode(unit_config_of(cell_file, "u"), context=ros.context)
    executor = SingleThreadedExecutor(context=ros.context)
    executor.add_node(unit)
    try:
        ros.add(EquipmentModule("robot", "u", cell, lease=LEASE, context=ros.context))
        deadline = time.monotonic() + 20
        while "robot" not in unit.liveliness.alive:  # the EM joins: the unit spins meanwhile
            assert time.monotonic() < deadline, "the EM never came online"
            executor.spin_once(timeout_sec=0.05)
        # the unit's executor held: heartbeats arrive and wait; its clock passes the lease
        seen = unit.liveliness.last_seen["robot"]
        while unit.steady() - seen <= LEASE + 0.2:  # (the leases run on the steady clock)
            assert time.monotonic() < deadline + 10, "the unit's clock did not move"
            time.sleep(0.01)  # (waiting for the unit's clock: the condition above)
        assert unit.liveliness.last_seen["robot"] == seen  # nothing was processed meanwhile
        unit._on_wake()  # the wake-up runs first, as in the loaded executor
        assert "robot" in unit.liveliness.alive  # judged after the queue: not yet
        while unit.liveliness.last_seen["robot"] == seen:  # the queue, then the next wake-up
            assert time.monotonic() < deadline + 20, "no heartbeat was handled"
            executor.spin_once(timeout_sec=0.05)
        for _ in range(20):
            executor.spin_once(timeout_sec=0.01)
        assert "robot" in unit.liveliness.alive
        assert unit.liveliness.last_seen["robot"] > seen + LEASE
        assert unit.unit.equipment.modules["robot"].online
    finally:
        executor.remove_node(unit)
        executor.shutdown(timeout_sec=1)
        unit.destroy_node()
