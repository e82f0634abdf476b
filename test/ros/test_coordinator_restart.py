"""Issue 25 item 13: a coordinator killed in the middle of a cell command. The restarted one says
which command was interrupted and which units it had reached, and resumes nothing."""

from __future__ import annotations

import time
from pathlib import Path

from packml_interfaces.msg import CellStatus
from packml_interfaces.srv import Command

from packml_ros2 import qos
from packml_ros2.core import Cmd
from packml_ros2.testing.processes import Processes
from test.ros.cells import UnitClient, start_em_process, start_unit_process, write_cell

SLOW_START = {"sim": {"durations": {"starting": 4.0}, "lease": 5.0}}


def test_a_restarted_coordinator_says_which_command_was_interrupted(
    ros, processes: Processes, tmp_path: Path
) -> None:
    units = {name: {"remote_commands_enabled": True, "equipment_modules": {f"{name}_em": SLOW_START}}
             for name in ("first", "second")}  # fmt: skip
    cell_file, cell = write_cell(tmp_path, units, {"start_order": ["first", "second"], "step_timeout": 20.0})  # fmt: skip
    for name in units:
        start_unit_process(processes, cell_file, name)
        start_em_process(processes, cell_file, name, f"{name}_em")
    coordinator = processes.module("coordinator", "packml_ros2.coordinator_node", str(cell_file))
    first, second = UnitClient(ros, cell, "first"), UnitClient(ros, cell, "second")
    status = ros.subscribe(CellStatus, f"/{cell}/coordinator/status", qos.CELL_STATUS)
    for unit in (first, second):
        unit.ready(30)
        unit.wait_status(lambda m: "RESET" in m.commands_valid_names, 30, "its EM online")
    status.wait_for(lambda m: m.all_online and len(m.units) == 2, 30, "both units online")
    service = f"/{cell}/coordinator/command"
    assert ros.call(
        Command, service, Command.Request(command=int(Cmd.RESET), source="operator"), 30
    ).accepted
    for unit in (first, second):
        unit.wait_state("IDLE", 15)
    starter = ros.node.create_client(Command, service)  # its answer never comes: not waited for
    starter.call_async(Command.Request(command=int(Cmd.START), source="operator"))
    first.wait_state("STARTING", 15)  # the first of the start order is starting (4 s)
    coordinator.kill()

    again = processes.module("coordinator_again", "packml_ros2.coordinator_node", str(cell_file))
    # What it says is in its log (the cell status carries it too, but a later status can replace
    # it before a subscriber that matches the new coordinator late reads the latched one).
    deadline = time.monotonic() + 30
    while "not resumed" not in again.output():
        assert time.monotonic() < deadline, f"no word of the interrupted command:\n{again.output()}"
        time.sleep(0.05)
    said = again.output()
    assert "START from operator" in said and "interrupted" in said, said
    assert "it had reached first; not second; not resumed" in said, said
    # never resumed: the first unit ends its Starting on its own, the second stays Idle
    first.wait_state("EXECUTE", 15)
    assert second.status.last.state_current_name == "IDLE"
    status.wait_for(lambda m: {u.name: u.state_current_name for u in m.units} == {"first": "EXECUTE", "second": "IDLE"}, 15, "mixed")  # fmt: skip
    assert second.status.last.state_current_name == "IDLE"
