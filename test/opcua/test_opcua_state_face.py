"""Issue 24 item 11: what the OPC UA face says follows the unit's state, as node-opcua
(test/opcua_client/client.mjs) reads it.

- ``Executable`` of a state machine method is true only when the method causes a transition out
  of the unit's current state in its mode (the rule book's graph), and
  ``AvailableTransitions`` are the transitions out of the current state (OPC 30050 6.3.5: "a
  StateMachine may restrict the States and Transitions that are currently available";
  AvailableStates stay those of the mode).
- A write is answered per node: ``BadNotWritable`` for a read-only variable or attribute, for a
  user and an anonymous session alike (no ServiceFault).
- Before a unit was ever seen its Admin values are ``Bad_WaitingForInitialData`` (no
  Uncertain_LastUsableValue without a value), and an Admin message stamped before the one written
  last is not written over it (AccTimeSinceReset never runs backwards).
"""

from __future__ import annotations

import datetime as dt
from pathlib import Path
from typing import Any

import pytest
import yaml
from builtin_interfaces.msg import Time
from packml_interfaces.srv import SetMode

from packml_ros2 import qos
from packml_ros2.core import Cmd
from packml_ros2.testing.processes import Processes, wait_until
from test.opcua import test_opcua
from test.opcua.test_opcua import (
    ES,
    EXECUTE_2022,
    MS,
    SM,
    UNIT,
    Cell,
    _official,
    free_port,
    start_face,
)
from test.ros.cells import UnitClient, write_cell

pytestmark = pytest.mark.ros
# the cell of test_opcua.py (one of its own for this module) and its filler, brought to Stopped
cell = test_opcua.cell
filler = test_opcua.filler

METHODS = {
    "Abort": SM, "Clear": SM, "Stop": MS, "Reset": MS,
    "ExecuteState/Reset": ES, "Start": ES, "Hold": ES, "Unhold": ES, "Suspend": ES,
    "Unsuspend": ES, "ToComplete": ES,
}  # fmt: skip


def _executable(cell: Cell) -> set[str]:
    steps = [{"op": "read", "path": f"{owner}/P:{name.rsplit('/', 1)[-1]}", "attribute": "Executable"}
             for name, owner in METHODS.items()]  # fmt: skip
    results = cell.run(steps)
    return {name for name, r in zip(METHODS, results, strict=True) if r["value"] is True}


def test_executable_and_available_transitions_follow_the_state(
    cell: Cell, filler: UnitClient
) -> None:
    names = {i: name for children in _official().values() for name, (i, _) in children.items()}

    def now() -> tuple[set[str], list[set[str]]]:
        state = filler.status.last.state_current
        steps = [{"op": "wait", "path": f"{UNIT}/P:Status/U:StateCurrent", "value": state}]
        steps += [{"op": "read", "path": f"{m}/0:AvailableTransitions"} for m in (SM, MS, ES)]
        _, *reads = cell.run(steps)
        transitions = []
        for r in reads:
            assert r["status"] == "Good", r
            transitions.append({names[int(v.split("i=")[1])] if ";i=" in v else "u:" + v.rsplit(".", 1)[1]
                                for v in r["value"]})  # fmt: skip
        return _executable(cell), transitions

    filler.wait_state("STOPPED")
    executable, transitions = now()
    assert executable == {"Abort", "Reset"}, executable
    assert transitions == [{"ClearedToAborting"}, {"StoppedToRunning"}, set()], transitions

    assert filler.command(Cmd.RESET).accepted
    filler.wait_state("IDLE")
    executable, transitions = now()
    assert executable == {"Abort", "Stop", "Start"}, executable
    assert transitions == [{"ClearedToAborting"}, {"RunningToStopping"}, {"IdleToStarting"}]

    assert filler.command(Cmd.START).accepted
    filler.wait_state("EXECUTE")
    executable, transitions = now()
    assert executable == {"Abort", "Stop", "Hold", "Suspend", "ToComplete"}, executable
    assert transitions[2] == {"ExecuteToHolding", "ExecuteToSuspending", "ExecuteToCompleting"}
    assert transitions[2] <= EXECUTE_2022

    # the mode decides too: Maintenance disables the Suspend group of this unit
    assert filler.command(Cmd.STOP).accepted
    filler.wait_state("STOPPED")
    filler.call(SetMode, "set_mode", mode=2, source="operator:test")
    filler.wait_status(lambda m: m.unit_mode_current == 2, 10, "maintenance")
    assert filler.command(Cmd.RESET).accepted
    filler.wait_state("IDLE")
    assert filler.command(Cmd.START).accepted
    filler.wait_state("EXECUTE")
    executable, transitions = now()
    assert executable == {"Abort", "Stop", "Hold", "ToComplete"}, executable
    assert transitions[2] == {"ExecuteToHolding", "ExecuteToCompleting"}, transitions


def test_writes_are_answered_per_node_with_bad_not_writable(cell: Cell, filler: UnitClient) -> None:
    steps = [
        {"op": "write", "path": f"{UNIT}/P:Status/P:MachSpeed", "value": {"type": "Float", "value": 5}},
        {"op": "write", "path": f"{UNIT}/P:Admin/P:AccTimeSinceReset", "value": {"type": "Int32", "value": 0}},
        {"op": "write", "path": f"{UNIT}/P:Status/P:MachSpeed", "attribute": "DisplayName",
         "value": {"type": "LocalizedText", "value": {"text": "x"}}},
        {"op": "read", "path": f"{UNIT}/P:Admin/P:AccTimeSinceReset"},
    ]  # fmt: skip
    for who, results in (("anonymous", cell.run(steps)), ("operator", cell.operator(steps))):
        assert [r.get("status") for r in results[:3]] == ["BadNotWritable"] * 3, (who, results)
        assert results[3]["status"] == "Good", (who, results)


def _epoch(iso: str) -> float:
    return dt.datetime.fromisoformat(iso.replace("Z", "+00:00")).timestamp()


def _time(t: float) -> Time:
    return Time(sec=int(t), nanosec=round(t % 1 * 1e9))


def test_admin_waits_for_initial_data_and_never_runs_backwards(
    tmp_path: Path, cell: Cell, ros: Any
) -> None:
    from packml_interfaces.msg import Admin, Status

    path, name = write_cell(tmp_path, {"filler": {}}, coordinator={"enabled": False, "unit_lease": 1.0})  # fmt: skip
    port = free_port()
    doc = yaml.safe_load(path.read_text())
    doc["opcua"] = {"port": port, "state_dir": str(tmp_path / "state")}
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    procs = Processes(tmp_path)
    try:
        start_face(procs, path, "opcua_early")
        url = f"opc.tcp://127.0.0.1:{port}/"
        admin = f"{UNIT}/P:Admin"
        # the unit never came: once its lease passed it is lost, its Status values Bad; its
        # Admin values have no last usable value
        names = (
            "AccTimeSinceReset",
            "MachDesignSpeed",
            "Alarm",
            "StopReason",
            "ProdProcessedCount",
        )
        lost, *reads = cell.client.job(url, [
            {"op": "wait", "path": f"{UNIT}/P:Status/P:UnitModeCurrent",
             "until": "s === 'BadCommunicationError'", "timeout": 20000},
            *({"op": "read", "path": f"{admin}/P:{n}"} for n in names),
        ], timeout=40)  # fmt: skip
        assert lost["status"] == "BadCommunicationError", lost
        assert [r["status"] for r in reads] == ["BadWaitingForInitialData"] * len(names), reads

        # an Admin stamped before the one written last is not written over it
        pub = ros.node.create_publisher(Admin, f"/{name}/filler/admin", qos.ADMIN)
        wait_until(lambda: pub.get_subscription_count() > 0, 10, 0.02, "the server's admin subscription")  # fmt: skip
        t = dt.datetime.now(dt.UTC).timestamp()
        pub.publish(Admin(stamp=_time(t + 1), acc_time_since_reset=510, mach_design_speed=50.0))
        cell.client.job(url, [{"op": "wait", "path": f"{admin}/P:AccTimeSinceReset",
                                          "value": 510, "timeout": 10000}])  # fmt: skip
        # the older one, then a status (another topic, written after it): once the status is
        # there, the older Admin was taken
        status = ros.node.create_publisher(Status, f"/{name}/filler/status", qos.STATUS)
        wait_until(lambda: status.get_subscription_count() > 0, 10, 0.02, "the server's status subscription")  # fmt: skip
        pub.publish(Admin(stamp=_time(t), acc_time_since_reset=509, mach_design_speed=77.0))
        status.publish(Status(stamp=_time(t + 3), state_current=2, unit_mode_current=1))

        def status_written() -> bool:
            (mode,) = cell.client.job(url, [{"op": "read", "path": f"{UNIT}/P:Status/P:UnitModeCurrent"}])  # fmt: skip
            stamp = mode.get("sourceTimestamp")
            return stamp is not None and abs(_epoch(stamp) - (t + 3)) < 0.01

        wait_until(status_written, 20, 0.05, "the status written")
        (after,) = cell.client.job(url, [{"op": "read", "path": f"{admin}/P:AccTimeSinceReset"}])
        # 510 was never replaced: the value (and its source time) are still those of t + 1
        assert after["value"] == 510, after
        assert abs(_epoch(after["sourceTimestamp"]) - (t + 1)) < 0.01, (after, t)
        ros.node.destroy_publisher(status)
        ros.node.destroy_publisher(pub)
    finally:
        failures = procs.close()
        assert not failures, failures
