"""Issue 8: a running cell seen through OPC UA by a client of another implementation (node-opcua,
test/opcua_client/client.mjs): OPC 30050 structure, StateCurrent, Reset and Start changing the
state, a refused command with its reason, alarms and counters, read-only anonymous sessions, the
Basic256Sha256 endpoint with a user password and with a user certificate, `packml launch --opcua`.

One cell for the module (two units as processes, a simulated EM, `packml opcua`), and one
long-running node process that runs each job (connect, steps, disconnect) sent on a line: loading
node-opcua costs seconds, paid once. Every wait is on a condition (a subscription, a topic, a line
of output), never a fixed sleep; everything listens on 127.0.0.1.
"""

from __future__ import annotations

import json
import os
import queue
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from packml_interfaces.srv import ResetAlarms, SetAlarm, SetMode

from packml_ros2.core import Cmd
from packml_ros2.opcua.config import hash_password
from packml_ros2.testing.processes import Processes, wait_until
from test.ros.cells import UnitClient, start_em_process, start_unit_process, write_cell

pytestmark = pytest.mark.ros

CLIENT_DIR = Path(__file__).resolve().parents[1] / "opcua_client"
PASSWORD = "op-secret-1"
UNIT = "P:PackMLObjects/U:filler"
SM = f"{UNIT}/P:BaseStateMachine"
MS = f"{SM}/P:MachineState"
ES = f"{MS}/P:ExecuteState"
FAST = {"resetting": 0.1, "starting": 0.1, "stopping": 0.1, "clearing": 0.1, "aborting": 0.05}


def _node_missing() -> str:
    if shutil.which("node") is None:
        return "node (Node.js) is not installed: the independent OPC UA client is node-opcua"
    if not (CLIENT_DIR / "node_modules" / "node-opcua-client").is_dir():
        return (
            "node-opcua is not installed: run tools/setup.sh --test (npm ci in test/opcua_client)"
        )
    return ""


if _node_missing():
    pytest.skip(_node_missing(), allow_module_level=True)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class NodeClient:
    """``node client.mjs --lines``: one JSON job per line, one JSON answer per line."""

    def __init__(self, log: Path, pki: Path) -> None:
        self.pki = pki
        self._log = log.open("wb")
        self.proc = subprocess.Popen(
            ["node", "client.mjs", "--lines"],
            cwd=CLIENT_DIR,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=self._log,
            text=True,
        )
        self._lines: queue.Queue[str] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self._lines.put(line)

    def _answer(self, timeout: float) -> dict[str, Any]:
        deadline = time.monotonic() + timeout
        while True:
            try:
                line = self._lines.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                raise AssertionError(
                    f"the node client did not answer within {timeout:g} s"
                ) from None
            if line.startswith("{"):
                return json.loads(line)

    def wait_ready(self, timeout: float = 60.0) -> None:
        assert self._answer(timeout) == {"ready": True}

    def job(
        self, url: str, steps: list[dict[str, Any]], timeout: float = 30.0, **opts: Any
    ) -> list[dict[str, Any]]:
        """Connect (``mode``, ``user``), run ``steps``, disconnect; the step results (a session
        that cannot be created raises AssertionError with the reason)."""
        assert self.proc.stdin is not None
        self.proc.stdin.write(
            json.dumps({"url": url, "pki": str(self.pki), "steps": steps, **opts}) + "\n"
        )
        self.proc.stdin.flush()
        answer = self._answer(timeout)
        if not answer["ok"]:
            raise AssertionError(answer["error"])
        return answer["results"]

    def close(self) -> None:
        if self.proc.stdin:
            self.proc.stdin.close()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self._log.close()


def client_certificate(folder: Path) -> tuple[Path, Path]:
    """A client application certificate (DER) and key (PEM) for an X509 user identity."""
    from asyncua.crypto import cert_gen
    from cryptography import x509
    from cryptography.hazmat.primitives.serialization import Encoding
    from cryptography.x509.oid import ExtendedKeyUsageOID

    key = cert_gen.generate_private_key()
    cert = cert_gen.generate_self_signed_app_certificate(
        key, "scada", {}, [x509.UniformResourceIdentifier("urn:test:scada")],
        [ExtendedKeyUsageOID.CLIENT_AUTH], days=30,
    )  # fmt: skip
    cert_file, key_file = folder / "scada.der", folder / "scada.pem"
    cert_file.write_bytes(cert.public_bytes(Encoding.DER))
    key_file.write_bytes(cert_gen.dump_private_key_as_pem(key))
    return cert_file, key_file


class Cell:
    def __init__(self, name: str, url: str, client: NodeClient, cert: Path, key: Path) -> None:
        self.name, self.url, self.client, self.cert, self.key = name, url, client, cert, key

    def run(self, steps: list[dict[str, Any]], **opts: Any) -> list[dict[str, Any]]:
        return self.client.job(self.url, steps, **opts)

    def operator(self, steps: list[dict[str, Any]], **opts: Any) -> list[dict[str, Any]]:
        return self.run(steps, user={"name": "operator", "password": PASSWORD}, **opts)


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cell]:
    tmp = tmp_path_factory.mktemp("opcua")
    cert, key = client_certificate(tmp)
    path, name = write_cell(
        tmp,
        {
            "filler": {
                "mach_speed": 40,
                "mach_design_speed": 50,
                "counters": {"processed": [{"id": 1, "name": "bottles", "unit": "pcs"}]},
                "alarms": [{"id": 201, "message": "Nozzle clogged", "category": 2, "em": "nozzle"}],
                "equipment_modules": {"nozzle": {"sim": {"durations": FAST, "cycle_time": 0.1}}},
            },
            "capper": {"description": "Capper downstream"},
        },
        coordinator={"enabled": False},
    )
    port = free_port()
    doc = yaml.safe_load(path.read_text())
    doc["opcua"] = {
        "port": port,
        "users": {"operator": hash_password(PASSWORD, iterations=1000)},
        "user_certificates": {"scada": str(cert)},
        "state_dir": str(tmp / "state"),
    }
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    (tmp / "logs").mkdir()
    procs = Processes(tmp / "logs")
    client = NodeClient(tmp / "logs" / "node_client.log", tmp / "pki")
    try:
        for unit in ("filler", "capper"):
            start_unit_process(procs, path, unit)
        start_em_process(procs, path, "filler", "nozzle")
        server = procs.module("opcua", "packml_ros2.cli.main", "opcua", str(path))
        client.wait_ready()
        wait_until(
            lambda: "OPC UA server for cell" in server.output() or not server.running(),
            60,
            0.05,
            "the OPC UA server",
        )
        assert server.running(), server.output()
        yield Cell(name, f"opc.tcp://127.0.0.1:{port}/", client, cert, key)
    finally:
        client.close()
        failures = procs.close()
        assert not failures, failures


@pytest.fixture
def filler(cell: Cell, ros: Any) -> UnitClient:
    """The filler over ROS, brought to Stopped in Production with no alarm first."""
    unit = UnitClient(ros, cell.name, "filler")
    unit.ready()
    unit.call(SetAlarm, "set_alarm", id=201, value=0, active=False, category=-1, source="test")
    unit.call(ResetAlarms, "reset_alarms", clear_first_out=True, source="test")
    status = unit.status.last
    if status.state_current_name != "STOPPED":
        if status.state_current_name not in ("ABORTING", "ABORTED"):
            unit.command(Cmd.ABORT)
        unit.wait_state("ABORTED")
        unit.command(Cmd.CLEAR)
        unit.wait_state("STOPPED")
    if unit.status.last.unit_mode_current != 1:
        unit.call(SetMode, "set_mode", mode=1, source="test")
    unit.wait_status(
        lambda m: (
            m.state_current_name == "STOPPED" and m.unit_mode_current == 1 and not m.active_alarms
        ),
        10,
        "stopped in production without alarms",
    )
    return unit


def test_opc30050_structure_and_state_current(cell: Cell, filler: UnitClient) -> None:
    # the bridge's first status may still be on its way when the test begins: wait for it first
    number, endpoints, units, obj, status, admin, machines, base_sm, state_current, execute, version, modes, type_ = cell.run([
        {"op": "wait", "path": f"{MS}/0:CurrentState/0:Number", "value": 2},
        {"op": "endpoints"},
        {"op": "browse", "path": "P:PackMLObjects"},
        {"op": "browse", "path": UNIT},
        {"op": "browse", "path": f"{UNIT}/P:Status"},
        {"op": "browse", "path": f"{UNIT}/P:Admin"},
        {"op": "browse", "path": MS},
        {"op": "read", "path": f"{SM}/0:CurrentState"},
        {"op": "read", "path": f"{UNIT}/P:Status/U:StateCurrent"},
        {"op": "read", "path": f"{ES}/0:CurrentState"},
        {"op": "read", "path": f"{UNIT}/P:PackMLVersion"},
        {"op": "read", "path": f"{UNIT}/P:Status/P:UnitSupportedModes"},
        {"op": "browse", "path": "/0:Types/0:ObjectTypes/0:BaseObjectType/P:PackMLBaseObjectType"},
    ])  # fmt: skip
    offered = {(e["mode"], e["policy"].rsplit("#", 1)[-1]) for e in endpoints["endpoints"]}
    assert offered == {
        ("None", "None"),
        ("Sign", "Basic256Sha256"),
        ("SignAndEncrypt", "Basic256Sha256"),
    }
    assert all(e["url"] == cell.url for e in endpoints["endpoints"])
    assert {"Anonymous", "UserName", "Certificate"} <= set(endpoints["endpoints"][2]["tokens"])

    def names(browse: dict[str, Any]) -> set[str]:
        return {n.split(":", 1)[1] for n in browse["names"]}

    assert {"filler", "capper"} <= names(units)
    assert {"Status", "Admin", "BaseStateMachine", "PackMLVersion", "TagID", "SetUnitMode",
            "SetMachSpeed", "SetParameter", "SetProduct"} <= names(obj)  # fmt: skip
    assert {"UnitModeCurrent", "UnitModeRequested", "UnitModeChangeInProgress", "StateRequested",
            "StateChangeInProgress", "MachSpeed", "CurMachSpeed", "EquipmentBlocked",
            "EquipmentStarved", "Parameter", "Product", "UnitSupportedModes"} <= names(status)  # fmt: skip
    assert {"Alarm", "AlarmExtent", "AlarmHistory", "AlarmHistoryExtent", "Warning", "StopReason",
            "ModeCurrentTime", "ModeCumulativeTime", "StateCurrentTime", "StateCumulativeTime",
            "ProdConsumedCount", "ProdProcessedCount", "ProdDefectiveCount", "AccTimeSinceReset",
            "MachDesignSpeed"} <= names(admin)  # fmt: skip
    assert {"CurrentState", "ExecuteState", "Stop", "Reset"} <= names(machines)
    assert {"Status", "Admin", "BaseStateMachine", "SetUnitMode", "SetMachSpeed"} <= names(type_)
    # StateCurrent: Stopped = 2, as CurrentState of the machine state machine and as the PackTag
    assert base_sm["value"]["text"] == "Cleared"
    assert number["value"] == 2
    assert state_current["status"] == "Good" and state_current["value"] == 2
    assert execute["status"] == "BadStateNotActive"  # Execute sub state machine: not active
    assert version["value"]["PackMLOPC"] == "1.1.0"
    assert modes["value"] == "ns=1;s=filler.UnitModeEnum"


def test_anonymous_sessions_cannot_call_methods(cell: Cell, filler: UnitClient) -> None:
    reset, stop, state = cell.run([
        {"op": "call", "path": f"{MS}/P:Reset"},
        {"op": "call", "path": f"{UNIT}/P:SetMachSpeed", "args": [{"type": "Float", "value": 1}]},
        {"op": "read", "path": f"{UNIT}/P:Status/U:StateCurrent"},
    ])  # fmt: skip
    for refused in (reset, stop):
        assert refused["status"] == "BadUserAccessDenied"
        assert "read-only" in refused["diagnostics"]["localizedText"]
    assert state["value"] == 2
    assert filler.status.last.state_current_name == "STOPPED"
    # a wrong password is not an anonymous session
    with pytest.raises(AssertionError, match="BadUserAccessDenied"):
        cell.run([], user={"name": "operator", "password": "wrong"})


def test_reset_start_and_a_refusal_with_its_reason(cell: Cell, filler: UnitClient) -> None:
    refused, reset, idle, start, execute, requested, base, machine, stop, stopped = cell.operator([
        {"op": "call", "path": f"{ES}/P:Start"},
        {"op": "call", "path": f"{MS}/P:Reset"},
        {"op": "wait", "path": f"{ES}/0:CurrentState/0:Number", "value": 4},
        {"op": "call", "path": f"{ES}/P:Start"},
        {"op": "wait", "path": f"{UNIT}/P:Status/U:StateCurrent", "value": 6},
        {"op": "read", "path": f"{UNIT}/P:Status/P:StateRequested"},
        {"op": "read", "path": f"{SM}/0:CurrentState"},
        {"op": "read", "path": f"{MS}/0:CurrentState"},
        {"op": "call", "path": f"{MS}/P:Stop"},
        {"op": "wait", "path": f"{MS}/0:CurrentState/0:Number", "value": 2},
    ])  # fmt: skip
    assert refused["status"] == "BadInvalidState"
    assert refused["diagnostics"]["symbolicId"] == "COMMAND_NOT_ALLOWED"
    assert "START not allowed in STOPPED" in refused["diagnostics"]["localizedText"]
    assert refused["diagnostics"]["additionalInfo"] == refused["diagnostics"]["localizedText"]
    assert reset["status"] == start["status"] == stop["status"] == "Good"
    assert idle["value"] == 4 and execute["value"] == 6 and stopped["value"] == 2
    assert requested["value"] == 6
    assert base["value"]["text"] == "Cleared" and machine["value"]["text"] == "Running"
    # the unit saw the commands from OPC UA, with the user
    filler.transitions.wait_for(lambda t: t.command == Cmd.STOP and t.source == "opcua:operator")
    sources = {(t.command, t.source) for t in filler.transitions.messages}
    assert {(Cmd.RESET, "opcua:operator"), (Cmd.START, "opcua:operator")} <= sources


def test_alarms_and_counters(cell: Cell, filler: UnitClient) -> None:
    filler.command(Cmd.RESET)
    filler.wait_state("IDLE")
    filler.command(Cmd.START)
    filler.wait_state("EXECUTE")
    (counted,) = cell.run([
        {"op": "wait", "path": f"{UNIT}/P:Admin/P:ProdProcessedCount", "until": "v[0].Count >= 2", "timeout": 15000},
    ])  # fmt: skip
    count = counted["value"][0]
    assert count["ID"] == 1 and count["Name"] == "bottles" and count["AccCount"] >= count["Count"]
    assert count["Unit"]["DisplayName"]["text"] == "pcs"

    raised = filler.call(
        SetAlarm, "set_alarm", id=201, value=0, active=True, category=-1, source="test"
    )
    assert raised.accepted, raised.message_out
    alarm, extent, stop_reason, history, machine = cell.run([
        {"op": "wait", "path": f"{UNIT}/P:Admin/P:Alarm", "until": "v.some(a => a.ID === 201 && a.Trigger)"},
        {"op": "read", "path": f"{UNIT}/P:Admin/P:AlarmExtent"},
        {"op": "wait", "path": f"{UNIT}/P:Admin/P:StopReason", "until": "v.ID === 201"},
        {"op": "read", "path": f"{UNIT}/P:Admin/P:AlarmHistory"},
        {"op": "wait", "path": f"{MS}/0:CurrentState/0:Number", "value": 2},  # category 2: Stop
    ])  # fmt: skip
    entry = next(a for a in alarm["value"] if a["ID"] == 201)
    assert entry["Message"] == "Nozzle clogged" and entry["Category"] == 2
    assert abs(time.time() - _epoch(entry["DateTime"])) < 120
    assert entry["AckDateTime"].startswith("1601-01-01")  # not acknowledged
    assert extent["value"] >= 1
    assert stop_reason["value"]["Message"] == "Nozzle clogged"
    assert any(a["ID"] == 201 for a in history["value"])
    assert machine["value"] == 2


def test_secure_channel_with_a_user_certificate_and_object_methods(
    cell: Cell, filler: UnitClient
) -> None:
    (modes,) = cell.run([{"op": "read", "path": f"{UNIT}/P:Status/P:UnitSupportedModes"}])
    enum = modes["value"]
    parameter = {
        "ID": 7,
        "Name": "fill volume",
        "Value": 500.5,
        "Unit": {"displayName": {"text": "ml"}},
    }
    speed, speed_now, mode, mode_now, unknown, back, params, params_now = cell.run(
        [
            {"op": "call", "path": f"{UNIT}/P:SetMachSpeed", "args": [{"type": "Float", "value": 33.5}]},
            {"op": "wait", "path": f"{UNIT}/P:Status/P:MachSpeed", "value": 33.5},
            {"op": "call", "path": f"{UNIT}/P:SetUnitMode",
             "args": [{"type": "NodeId", "value": enum}, {"type": "Int32", "value": 2}]},
            {"op": "wait", "path": f"{UNIT}/P:Status/P:UnitModeCurrent", "value": 2},
            {"op": "call", "path": f"{UNIT}/P:SetUnitMode",
             "args": [{"type": "NodeId", "value": enum}, {"type": "Int32", "value": 9}]},
            {"op": "call", "path": f"{UNIT}/P:SetUnitMode",
             "args": [{"type": "NodeId", "value": enum}, {"type": "Int32", "value": 1}]},
            {"op": "call", "path": f"{UNIT}/P:SetParameter",
             "args": [{"type": "ExtensionObject", "dataType": "P:i=16", "array": True, "value": [parameter]}]},
            {"op": "wait", "path": f"{UNIT}/P:Status/P:Parameter", "until": "v.some(p => p.ID === 7)"},
        ],
        mode="SignAndEncrypt",
        policy="Basic256Sha256",
        user={"certificate": str(cell.cert), "key": str(cell.key)},
    )  # fmt: skip
    assert speed["status"] == mode["status"] == back["status"] == "Good"
    assert speed_now["value"] == 33.5 and mode_now["value"] == 2
    assert unknown["status"] == "BadOutOfRange" and "9" in unknown["diagnostics"]["localizedText"]
    assert params["status"] == "Good"
    (set_,) = [p for p in params_now["value"] if p["ID"] == 7]
    assert set_["Name"] == "fill volume" and set_["Value"] == 500.5
    assert set_["Unit"]["DisplayName"]["text"] == "ml"
    changes = filler.transitions.wait_for(lambda t: t.to_mode == 2, 10, "mode change")
    assert changes.source == "opcua:scada"
    filler.wait_status(lambda m: m.unit_mode_current == 1, 10, "production again")


def _epoch(iso: str) -> float:
    from datetime import datetime

    return datetime.fromisoformat(iso.replace("Z", "+00:00")).timestamp()


def test_packml_launch_with_opcua(tmp_path: Path, cell: Cell) -> None:
    """`packml launch --opcua PORT`: the cell and its OPC UA server; Ctrl-C stops both."""
    port = free_port()
    path, _ = write_cell(tmp_path, {"solo": {}}, coordinator={"enabled": False})
    doc = yaml.safe_load(path.read_text())
    doc["opcua"] = {"state_dir": str(tmp_path / "state"), "security_policies": ["None"]}
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    log = tmp_path / "launch.log"
    with log.open("wb") as out:
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "packml_ros2.cli.main",
                "launch",
                str(path),
                "--opcua",
                str(port),
            ],
            stdout=out,
            stderr=subprocess.STDOUT,
            env=dict(os.environ, PYTHONUNBUFFERED="1"),
        )
        try:

            def ready() -> bool:
                text = log.read_text()
                return ("is up" in text and "OPC UA server" in text) or proc.poll() is not None

            wait_until(ready, 60, 0.05, "the cell and its OPC UA server")
            assert proc.poll() is None, log.read_text()
            assert f"opc.tcp://127.0.0.1:{port}/" in log.read_text()
            (state,) = cell.client.job(
                f"opc.tcp://127.0.0.1:{port}/",
                [
                    {
                        "op": "wait",
                        "path": "P:PackMLObjects/U:solo/P:Status/U:StateCurrent",
                        "value": 2,
                    }
                ],
            )
            assert state["value"] == 2
            proc.send_signal(signal.SIGINT)
            assert proc.wait(30) == 0, log.read_text()
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    # the OPC UA server stopped with the cell: nothing listens on the port any more
    with socket.socket() as s:
        assert s.connect_ex(("127.0.0.1", port)) != 0
