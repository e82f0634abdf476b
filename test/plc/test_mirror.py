"""Issue 20, the pure part of the PLC bridge: how the values of an OPC 30050 object become a
unit's state, transitions (with trigger and source), valid commands and refusals, and how the
``plc:`` block of a cell file is checked (no OPC UA, no ROS)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml

from packml_ros2.core import Cmd, load_cell
from packml_ros2.core.config import unit_config
from packml_ros2.core.reasons import Reason
from packml_ros2.core.schema import ConfigError
from packml_ros2.core.unit import Trigger
from packml_ros2.opcua.nodeset import load
from packml_ros2.plc.config import parse_plc
from packml_ros2.plc.mirror import Mirror, plc_refusal

B, M, E = (
    "BaseStateMachine",
    "BaseStateMachine/MachineState",
    "BaseStateMachine/MachineState/ExecuteState",
)
MODEL = load()
IDS = {(m.name, s.name): s.id for m in MODEL.machines for s in m.states}


def ids(state: str) -> dict[str, Any]:
    """The CurrentState/Id values a PLC shows in ``state`` (NodeSet ids; -1: not active)."""
    if state in ("Aborting", "Aborted"):
        return {f"{B}/CurrentState/Id": IDS[("BaseStateMachine", state)]}
    base = {f"{B}/CurrentState/Id": IDS[("BaseStateMachine", "Cleared")]}
    if state in ("Clearing", "Stopped", "Stopping"):
        return {**base, f"{M}/CurrentState/Id": IDS[("MachineState", state)]}
    return {
        **base,
        f"{M}/CurrentState/Id": IDS[("MachineState", "Running")],
        f"{E}/CurrentState/Id": IDS[("ExecuteState", state)],
    }


def mirror(state: str = "Stopped", **values: Any) -> Mirror:
    m = Mirror(unit_config("wrapper"), MODEL)
    m.connected({**ids(state), "Status/UnitModeCurrent": 1, **values}, 0.0, "connected")
    return m


def test_the_state_is_read_through_the_nested_machines_and_never_from_an_inactive_one() -> None:
    m = mirror("Stopped")
    assert m.state.name == "STOPPED"
    # ExecuteState still shows Execute from before: MachineState (Stopped) decides
    m.values[f"{E}/CurrentState/Id"] = IDS[("ExecuteState", "Execute")]
    assert m.read_state()[0].name == "STOPPED"
    # a PLC without Ids: the state names (LocalizedText) and StateNumbers serve as well
    by_name = Mirror(unit_config("wrapper"), MODEL)
    by_name.connected({f"{B}/CurrentState": "Cleared", f"{M}/CurrentState": "Running",
                       f"{E}/CurrentState": "Idle", "Status/UnitModeCurrent": 1}, 0.0, "")  # fmt: skip
    assert by_name.state.name == "IDLE"
    by_number = Mirror(unit_config("wrapper"), MODEL)
    by_number.connected({f"{B}/CurrentState/Number": 19, f"{M}/CurrentState/Number": 2,
                         "Status/UnitModeCurrent": 1}, 0.0, "")  # fmt: skip
    assert by_number.state.name == "STOPPED"


def test_a_batch_that_enters_running_without_the_inner_state_waits_for_it() -> None:
    m = mirror("Stopped")
    m.values[f"{E}/CurrentState/Id"] = IDS[("ExecuteState", "Execute")]  # stale, from before
    # MachineState moved to Running; ExecuteState's new value is not in this batch
    assert m.update({f"{M}/CurrentState/Id": IDS[("MachineState", "Running")]}, 1.0) == []
    # ... it comes with the next publish: one transition, to Resetting, not via Execute
    (t,) = m.update({f"{E}/CurrentState/Id": IDS[("ExecuteState", "Resetting")]}, 1.05)
    assert (t.from_state.name, t.to_state.name) == ("STOPPED", "RESETTING")
    # when the inner value never comes, the change is taken after HOLD with what is there
    m2 = mirror("Execute")
    m2.expect(Cmd.STOP, "operator", 1.9)
    m2.update(ids("Stopped"), 2.0)
    m2.expect(Cmd.RESET, "operator", 2.9)
    m2.values[f"{E}/CurrentState/Id"] = IDS[("ExecuteState", "Idle")]
    assert m2.update({f"{M}/CurrentState/Id": IDS[("MachineState", "Running")]}, 3.0) == []
    assert m2.tick(3.1) == []
    (late,) = m2.tick(3.4)
    assert (late.from_state.name, late.to_state.name, late.source) == (
        "STOPPED",
        "IDLE",
        "operator",
    )


def test_transitions_carry_the_trigger_and_source_a_unit_would_give() -> None:
    m = mirror("Stopped")
    (first,) = m.connected({**ids("Stopped"), "Status/UnitModeCurrent": 1}, 0.0, "connected to X")
    assert (first.trigger, first.source, first.detail) == (Trigger.RESTART, "plc", "connected to X")
    # a command the bridge sent: its command and source, the acting state it passed skipped
    m.expect(Cmd.RESET, "remote:coordinator", 1.0)
    (t,) = m.update(ids("Idle"), 1.2)
    assert (t.trigger, t.command, t.source) == (Trigger.COMMAND, Cmd.RESET, "remote:coordinator")
    assert [s.name for s in t.skipped] == ["RESETTING"]
    assert m.cntrl_cmd == Cmd.RESET
    m.expect(Cmd.START, "operator", 2.0)
    (t,) = m.update(ids("Starting"), 2.1)
    assert (t.trigger, t.command) == (Trigger.COMMAND, Cmd.START)
    (t,) = m.update(ids("Execute"), 2.3)  # the PLC's own State Complete
    assert (t.trigger, t.source) == (Trigger.STATE_COMPLETE, "plc")
    # the PLC stops by itself with a fresh StopReason: an alarm transition naming it
    reason = {"ID": 3001, "Value": 0, "Message": "Film break", "Category": 2, "Trigger": True}
    (t,) = m.update({**ids("Stopping"), "Admin/StopReason": reason, "Admin/Alarm": [reason]}, 3.0)
    assert (t.trigger, t.command, t.source) == (Trigger.ALARM, Cmd.STOP, "alarm:3001")
    assert "Film break" in t.detail
    assert m.stop_reason().id == 3001 and m.banner() == "3001/0 Film break"
    (t,) = m.update(ids("Stopped"), 3.2)
    assert t.trigger == Trigger.STATE_COMPLETE
    # a command given at the PLC's own panel (nothing new in StopReason or alarms)
    # (the alarm is still active, but it was there when Stopped was entered): after HOLD
    assert m.update(ids("Aborting"), 4.0) == []
    (t,) = m.tick(4.31)
    assert (t.trigger, t.command, t.source) == (Trigger.COMMAND, Cmd.ABORT, "plc")
    (t,) = m.update(ids("Aborted"), 4.4)
    assert m.sequence == t.sequence == 9
    # a mode change
    (t,) = m.update({"Status/UnitModeCurrent": 2}, 5.0)
    assert (t.trigger, t.from_mode, t.to_mode, t.source) == (Trigger.MODE, 1, 2, "plc")


def test_a_stop_made_by_the_plc_waits_for_its_cause_a_moment() -> None:
    m = mirror("Execute")
    # the state first, its StopReason in the next publish: still the alarm's transition
    assert m.update(ids("Stopping"), 1.0) == []
    reason = {"ID": 7, "Value": 2, "Message": "Guard door", "Category": 0, "Trigger": True}
    (t,) = m.update({"Admin/StopReason": reason}, 1.1)
    assert (t.trigger, t.source, t.detail) == (Trigger.ALARM, "alarm:7", "Guard door")  # fmt: skip
    # no cause within HOLD: a command given at the PLC itself
    m = mirror("Execute")
    assert m.update(ids("Holding"), 1.0) == []
    assert m.tick(1.2) == []
    (t,) = m.tick(1.31)
    assert (t.trigger, t.command, t.source) == (Trigger.COMMAND, Cmd.HOLD, "plc")
    assert t.detail == "HOLD given at the PLC"


def test_valid_commands_methods_and_refusals_follow_the_units_rules() -> None:
    m = mirror("Stopped")
    assert [c.name for c in m.valid_commands()] == ["RESET", "ABORT"]
    assert m.refusal(Cmd.START) == (
        "START not allowed in STOPPED in PRODUCTION mode (valid now: RESET, ABORT)"
    )
    assert m.refusal(Cmd.RESET) is None
    assert "not a PackML command" in (m.refusal(42) or "")
    # the method of the innermost active machine that has it
    assert m.method_for(Cmd.RESET) == f"{M}/Reset"
    assert m.method_for(Cmd.ABORT) == f"{B}/Abort"
    complete = mirror("Complete")
    assert complete.method_for(Cmd.RESET) == f"{E}/Reset"
    assert mirror("Execute").method_for(Cmd.STOP) == f"{M}/Stop"
    assert mirror("Starting").state_requested().name == "EXECUTE"
    assert mirror("Stopping", **{"Status/StateRequested": 2}).state_requested().name == "STOPPED"


@pytest.mark.parametrize(
    ("status", "mode", "reason"),
    [
        ("BadInvalidState", False, Reason.COMMAND_NOT_ALLOWED),
        ("BadInvalidState", True, Reason.MODE_CHANGE_NOT_ALLOWED),
        ("BadOutOfRange", True, Reason.MODE_UNKNOWN),
        ("BadUserAccessDenied", False, Reason.UNAUTHORIZED),
        ("BadNotImplemented", False, Reason.NOT_SUPPORTED),
        ("BadTimeout", False, Reason.UNIT_UNAVAILABLE),
        ("BadSomethingNew", False, Reason.COMMAND_NOT_ALLOWED),
    ],
)
def test_plc_refusals_become_reason_codes_and_sentences(status: str, mode: bool, reason: Reason) -> None:  # fmt: skip
    got, text = plc_refusal(
        "RESET", "STOPPED in PRODUCTION mode", status, "alarm 3001 active", mode
    )
    assert got == reason
    assert (
        text
        == f"RESET refused by the PLC in STOPPED in PRODUCTION mode ({status}: alarm 3001 active)"
    )


# -- the plc: block ------------------------------------------------------------------------------------------
def cell_file(tmp_path: Path, plc: dict[str, Any], **unit: Any) -> Path:
    doc = {"cell": "line", "units": {"wrapper": {"plc": plc, **unit}},
           "coordinator": {"unit_lease": 2.0}}  # fmt: skip
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def problems(path: Path) -> str:
    with pytest.raises(ConfigError) as exc:
        parse_plc(load_cell(path), "wrapper")
    return str(exc.value)


def test_the_plc_block_defaults_and_secrets(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = cell_file(tmp_path, {"endpoint": "opc.tcp://127.0.0.1:4840"})
    plc = parse_plc(load_cell(path), "wrapper")
    assert (plc.browse_path, plc.lease, plc.security_policy, plc.user) == (
        ("PackMLObjects", "wrapper"), 2.0, "None", "")  # fmt: skip
    monkeypatch.setenv("WRAPPER_PLC_PASSWORD", "s3cret-pw")
    (tmp_path / "pw").write_text("from-a-file\n")
    for ref, expected in (("env:WRAPPER_PLC_PASSWORD", "s3cret-pw"), ("file:pw", "from-a-file")):
        path = cell_file(tmp_path, {"endpoint": "opc.tcp://h:4840", "user": "packml", "password": ref,
                                    "security_policy": "Basic256Sha256"})  # fmt: skip
        plc = parse_plc(load_cell(path), "wrapper")
        assert plc.password == expected and plc.security_mode == "SignAndEncrypt"
        assert expected not in repr(plc)


def test_the_plc_block_refuses_what_cannot_work(tmp_path: Path) -> None:
    # a password written in the file is refused by the cell file's loader, as every secret is
    text = problems(cell_file(tmp_path, {"endpoint": "opc.tcp://h:1", "user": "u",
                                         "password": "written-in-the-file"}))  # fmt: skip
    assert "units.wrapper.plc.password: a secret is never written in the cell file" in text
    assert "written-in-the-file" not in text
    text = problems(cell_file(tmp_path, {"endpoint": "http://x", "lease": 5, "user": "u",
                                         "password": "env:UNUSED", "bogus": 1,
                                         "security_policy": "None", "security_mode": "Sign"},
                              equipment_modules={"infeed": {}}))  # fmt: skip
    assert "units.wrapper.plc.endpoint: 'http://x' is not an OPC UA endpoint" in text
    assert "units.wrapper.plc.lease: 5 s is longer than coordinator.unit_lease 2 s" in text
    assert "units.wrapper.plc.bogus: unknown key" in text
    assert (
        "units.wrapper.plc.security_mode: security_policy None goes with security_mode None" in text
    )
    assert "units.wrapper.equipment_modules: a PLC unit's equipment modules live in the PLC" in text
    assert "missing key 'endpoint'" in problems(cell_file(tmp_path, {}))
    assert "environment variable NOT_SET_ANYWHERE is not set" in problems(
        cell_file(
            tmp_path, {"endpoint": "opc.tcp://h:1", "user": "u", "password": "env:NOT_SET_ANYWHERE"}
        )
    )


def test_packml_launch_starts_a_bridge_for_each_plc_unit(tmp_path: Path) -> None:
    from packml_ros2.launcher import node_specs, plan

    path = cell_file(tmp_path, {"endpoint": "opc.tcp://127.0.0.1:4840"})
    doc = yaml.safe_load(path.read_text())
    doc["units"]["robot"] = {"equipment_modules": {"gripper": {"sim": {}}}}
    path.write_text(yaml.safe_dump(doc))
    specs = {s.name: (s.executable, s.module, s.arguments) for s in node_specs(plan(path))}
    assert specs["plc wrapper"] == ("plc_bridge", "packml_ros2.plc.node", (str(path), "wrapper"))
    assert specs["unit robot"][0] == "unit_node" and "unit wrapper" not in specs
    # the launcher validates the plc: block before anything starts
    bad = cell_file(tmp_path, {"endpoint": "opc.tcp://h:1", "lease": 9})
    with pytest.raises(ConfigError, match=r"units\.wrapper\.plc\.lease"):
        plan(bad)
