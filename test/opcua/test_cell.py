"""The cell object's translation (:mod:`packml_ros2.opcua.cell`): the coordinator's CellStatus
and stop episodes as the Status and Admin a unit object is written from."""

from __future__ import annotations

from packml_interfaces.msg import Alarm, CellStatus, LineEpisode, UnitSummary

from packml_ros2.core import parse_cell
from packml_ros2.opcua.cell import cell_admin, cell_status, cell_unit, valid


def test_the_status_is_the_coordinators_aggregate() -> None:
    msg = CellStatus(cell="c", state_current=6, state_current_name="EXECUTE", unit_mode_current=1,
                     busy=True, commands_valid=[3, 4], commands_valid_names=["STOP", "HOLD"],
                     units=[UnitSummary(name="a"), UnitSummary(name="b", starved=True)])  # fmt: skip
    msg.stamp.sec = 7
    status = cell_status(msg)
    assert (status.state_current, status.state_requested, status.unit_mode_current) == (6, 6, 1)
    assert status.state_change_in_process  # a cell command sequence runs
    assert (status.equipment_interlock.blocked, status.equipment_interlock.starved) == (False, True)
    assert list(status.commands_valid) == [3, 4] and status.stamp.sec == 7
    assert valid(status, "BaseStateMachine/MachineState/Stop")
    assert not valid(status, "BaseStateMachine/MachineState/Reset")
    assert not valid(None, "BaseStateMachine/MachineState/Stop")
    assert not valid(status, "BaseStateMachine/NoSuchMethod")


def test_the_stop_reason_names_the_unit_the_episode_started_at() -> None:
    known = LineEpisode(root_unit="robot", reason="alarm 301: Gripper jammed", source="alarm:301",
                        stop_reason_known=True, stop_reason=Alarm(id=301, message="Gripper jammed"))  # fmt: skip
    admin = cell_admin(known)
    assert admin.stop_reason_extent == 1
    assert (admin.stop_reason.id, admin.stop_reason.message) == (301, "robot: Gripper jammed")
    assert admin.stop_reason.source == "alarm:301"
    assert known.stop_reason.message == "Gripper jammed"  # the episode is not changed
    unknown = cell_admin(LineEpisode(root_unit="", reason="STOP from operator", source="operator"))
    assert (unknown.stop_reason.id, unknown.stop_reason.message) == (0, "cell: STOP from operator")


def test_the_object_is_drawn_with_the_first_units_rules() -> None:
    cell = parse_cell({"cell": "c", "units": {"a": {"model": "2015"}, "b": {}},
                       "coordinator": {"start_order": ["b", "a"]}})  # fmt: skip
    unit = cell_unit(cell)
    assert unit.name == "c" and unit.table is cell.units["b"].table
    assert "a, b" in unit.description and not unit.recipes.recipes
