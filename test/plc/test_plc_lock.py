"""Issue 15: the remote lock of a PLC unit over DDS, as of a ROS unit. With
``remote_commands_enabled: false`` every request from a remote source (``hmi:``, ``opcua:``,
``remote:``, the coordinator's interlock) that would change the PLC unit is refused with
REMOTE_DISABLED and nothing changes: no transition, the PLC's state and mode as they were. A
source outside the grammar (``REMOTE:x``) is INVALID_ARGUMENT. The lock itself is switched only
from a local source (not by ``ros2 param set``, not by a remote source); switched on, the same
remote command is accepted."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from packml_interfaces.msg import Result
from packml_interfaces.srv import (
    SetInterlock,
    SetMachSpeed,
    SetMode,
    SetProduct,
    SetRemoteCommands,
    SetUnitParameters,
)
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType, ParameterValue
from rcl_interfaces.srv import GetParameters, SetParameters

from packml_ros2.core import Cmd
from packml_ros2.testing.processes import Processes
from test.plc import test_plc_line
from test.plc.test_plc_line import PLC_MODULE, TestPlc
from test.ros.cells import UnitClient, write_cell

pytestmark = pytest.mark.ros

plc = test_plc_line.plc  # the fixture: a PLC (node plc.mjs) on a free port
REMOTE = ("remote:mes", "hmi:eve", "opcua:scada", "coordinator")


def test_a_locked_plc_unit_refuses_every_remote_request_and_only_a_local_source_unlocks_it(
    tmp_path: Path, ros: Any, processes: Processes, plc: TestPlc
) -> None:
    endpoint = f"opc.tcp://127.0.0.1:{plc.options['port']}"
    path, cell = write_cell(
        tmp_path,
        {"wrapper": {"remote_commands_enabled": False, "plc": {"endpoint": endpoint}}},
    )
    processes.module("plc_wrapper", PLC_MODULE, str(path), "wrapper")
    wrapper = UnitClient(ros, cell, "wrapper")
    wrapper.ready(30)
    wrapper.transitions.wait_for(lambda t: True, 10, "the bridge connected")
    before = wrapper.wait_status(lambda m: True)
    assert not before.remote_commands_enabled
    transitions = len(wrapper.transitions)
    while not plc.lines.empty():  # the PLC's transitions so far
        plc.lines.get_nowait()

    def refused(resp: Any, source: str, what: str) -> None:
        assert not resp.accepted and resp.result == Result.REMOTE_DISABLED, f"{what}: {resp}"
        assert source in resp.message and "remote commands are disabled" in resp.message, what

    for source in REMOTE:
        for cmd in (Cmd.RESET, Cmd.START, Cmd.STOP, Cmd.ABORT):
            refused(wrapper.command(cmd, source), source, f"{cmd.name} from {source}")
        refused(wrapper.call(SetMode, "set_mode", mode=2, source=source), source, "mode")
        refused(
            wrapper.call(SetMachSpeed, "set_mach_speed", mach_speed=10.0, source=source),
            source,
            "speed",
        )
        refused(wrapper.call(SetUnitParameters, "set_unit_parameters", source=source), source, "parameters")  # fmt: skip
        refused(wrapper.call(SetProduct, "set_product", source=source), source, "product")
        refused(
            wrapper.call(SetInterlock, "set_interlock", active=True, reason="x", source=source),
            source,
            "interlock",
        )
    for source in ("REMOTE:mes", " remote:mes", "Hmi:eve"):  # no case or space bypass
        resp = wrapper.command(Cmd.RESET, source)
        assert not resp.accepted and resp.result == Result.INVALID_ARGUMENT, (source, resp)

    # the lock itself: not from a remote source, not by ros2 param set
    for source in REMOTE:
        resp = wrapper.call(SetRemoteCommands, "set_remote_commands", enabled=True, source=source)
        assert not resp.accepted and "only from a local source" in resp.message, resp
    param = ParameterMsg(
        name="remote_commands_enabled",
        value=ParameterValue(type=ParameterType.PARAMETER_BOOL, bool_value=True),
    )
    result = ros.call(SetParameters, f"/{cell}/wrapper/set_parameters", SetParameters.Request(parameters=[param]))  # fmt: skip
    assert not result.results[0].successful and "set_remote_commands" in result.results[0].reason
    got = ros.call(GetParameters, f"/{cell}/wrapper/get_parameters", GetParameters.Request(names=["remote_commands_enabled"]))  # fmt: skip
    assert got.values[0].bool_value is False

    # nothing changed: no transition of the unit or of the PLC, the same state, mode and speed
    # (the status is published periodically: the newest one shows it)
    now = wrapper.wait_status(lambda m: True)
    assert len(wrapper.transitions) == transitions
    assert plc.lines.empty(), plc.lines.get_nowait()
    assert (now.state_current, now.unit_mode_current, now.mach_speed, now.remote_commands_enabled) == (
        before.state_current, before.unit_mode_current, before.mach_speed, False,
    )  # fmt: skip

    # switched by the operator, the same remote command is taken
    resp = wrapper.call(SetRemoteCommands, "set_remote_commands", enabled=True, source="operator")
    assert resp.accepted, resp
    wrapper.wait_status(lambda m: m.remote_commands_enabled, 10, "the lock off")
    resp = wrapper.command(Cmd.RESET, "remote:mes")
    assert resp.accepted, resp
    line = plc.lines.get(timeout=10)
    assert line.get("name") in ("RESETTING", "IDLE"), line

    # an interlock the coordinator set is released by it after the unit was switched to local
    # (the lock guards setting one, as on a ROS unit: core.interlocks.interlock_refusal)
    held = wrapper.call(SetInterlock, "set_interlock", active=True, reason="packer blocked", source="coordinator")  # fmt: skip
    assert held.accepted, held
    assert wrapper.call(SetRemoteCommands, "set_remote_commands", enabled=False, source="operator").accepted  # fmt: skip
    again = wrapper.call(SetInterlock, "set_interlock", active=True, reason="again", source="coordinator")  # fmt: skip
    assert again.result == Result.REMOTE_DISABLED, again
    other = wrapper.call(SetInterlock, "set_interlock", active=False, source="remote:mes")
    assert other.result == Result.NOTHING_TO_DO, other
    cleared = wrapper.call(SetInterlock, "set_interlock", active=False, source="coordinator")
    assert cleared.accepted and "cleared" in cleared.message, cleared
