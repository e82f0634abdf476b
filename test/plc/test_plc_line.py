"""Issue 20: PLC PackML units (OPC 30050 servers) in a ROS line, through the bridge
(``plc_bridge``, :mod:`packml_ros2.plc`).

The "PLC" is an OPC UA server of another implementation: ``test/opcua_client/plc.mjs``
(node-opcua with the official PackML NodeSet of node-opcua-nodesets, running its own state
machine). A mixed line (a ROS unit with a simulated EM, the PLC unit, the coordinator; every node
a process) is reset and started by the coordinator, propagates interlocks both ways, stops when
the PLC faults (its stop reason visible), recovers, and survives the PLC process being killed
and restarted, and frozen (SIGSTOP: no FIN, only silence) and thawed: the loss is seen within the
lease, the link comes back by itself, nothing is stuck. The second target is this project's own
OPC UA face (``packml opcua``), reached with Basic256Sha256 SignAndEncrypt and a user whose
password comes from the environment: commands, an alarm stop, and a refusal whose reason is the
server's diagnostics. Every wait is on a condition; everything listens on 127.0.0.1.
"""

from __future__ import annotations

import json
import os
import queue
import signal
import subprocess
import threading
import time
from functools import partial
from pathlib import Path
from typing import Any

import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from packml_interfaces.msg import CellStatus, LineEpisode, Result, TransitionEvent
from packml_interfaces.srv import Command, SetAlarm
from rclpy.node import Node
from rclpy.serialization import deserialize_message
from std_srvs.srv import SetBool

from packml_ros2 import qos
from packml_ros2.bag.recording import load
from packml_ros2.core import Cmd, load_cell
from packml_ros2.hmi.bridge import Bridge
from packml_ros2.opcua.config import hash_password
from packml_ros2.presence import Presence
from packml_ros2.testing.processes import Processes, wait_until
from test.opcua.test_opcua import CLIENT_DIR, free_port, start_face
from test.ros.cells import UnitClient, start_em_process, start_unit_process, write_cell
from test.test_replay import PACKML, ROOT, Output, packml

pytestmark = pytest.mark.ros

LEASE = 2.0
FAST = {"resetting": 0.1, "starting": 0.1, "stopping": 0.1, "clearing": 0.1, "aborting": 0.05}
PLC_MODULE = "packml_ros2.plc.node"

if not (CLIENT_DIR / "node_modules" / "node-opcua-server").is_dir():
    pytest.skip("node-opcua-server is not installed: run tools/setup.sh --test", allow_module_level=True)  # fmt: skip


class TestPlc:
    """``node plc.mjs``: an OPC 30050 server with its own state machine, driven over stdin."""

    __test__ = False

    def __init__(self, log_dir: Path, port: int, **options: Any) -> None:
        self.options = {"port": port, "unit": "wrapper", "dwell": 100, **options}
        self.log_dir = log_dir
        self.proc: subprocess.Popen[str] | None = None
        self.lines: queue.Queue[dict[str, Any]] = queue.Queue()

    def start(self) -> None:
        log = (self.log_dir / "plc.log").open("a")
        self.proc = subprocess.Popen(
            ["node", "plc.mjs", json.dumps(self.options)],
            cwd=CLIENT_DIR, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=log, text=True,
        )  # fmt: skip
        self.lines = queue.Queue()
        threading.Thread(target=self._read, args=(self.proc, self.lines), daemon=True).start()
        assert self.lines.get(timeout=60).get("ready"), "the test PLC did not start"

    @staticmethod
    def _read(proc: subprocess.Popen[str], lines: queue.Queue[dict[str, Any]]) -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            if line.startswith("{"):
                lines.put(json.loads(line))
                print(f"{time.time():.3f} plc: {line.strip()}", flush=True)

    def send(self, **msg: Any) -> None:
        assert self.proc is not None and self.proc.stdin is not None
        self.proc.stdin.write(json.dumps(msg) + "\n")
        self.proc.stdin.flush()

    def signal(self, sig: int) -> None:
        assert self.proc is not None
        self.proc.send_signal(sig)

    def kill(self) -> None:
        assert self.proc is not None
        self.proc.kill()
        self.proc.wait(10)

    def close(self) -> None:
        if self.proc is None or self.proc.poll() is not None:
            return
        self.proc.send_signal(signal.SIGCONT)
        assert self.proc.stdin is not None
        self.proc.stdin.close()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


class Line:
    """The coordinator's view and services of a cell, seen from the test."""

    def __init__(self, ros: Any, cell: str) -> None:
        self.ros, self.cell = ros, cell
        self.status = ros.subscribe(CellStatus, f"/{cell}/coordinator/status", qos.CELL_STATUS)
        self._since = 0

    def mark(self) -> None:
        """:meth:`wait` looks at cell statuses from the last one on."""
        self._since = max(0, len(self.status) - 1)

    def command(self, cmd: Cmd, timeout: float = 30.0) -> Command.Response:
        self.mark()
        return self.ros.call(Command, f"/{self.cell}/coordinator/command",
                             Command.Request(command=int(cmd), source="operator"), timeout)  # fmt: skip

    def wait(self, predicate: Any, what: str, timeout: float = 15.0) -> CellStatus:
        return self.status.wait_for(predicate, timeout, what, self._since)

    @staticmethod
    def unit(status: CellStatus, name: str) -> Any:
        return next(u for u in status.units if u.name == name)


def affected(episode: LineEpisode) -> set[tuple[str, str]]:
    return {(d.unit, d.how) for d in episode.affected}


def from_now(*units: UnitClient) -> None:
    """Waits on ``units`` look at what arrives from now on (as after a call through them)."""
    for unit in units:
        unit._since, unit._transitions_since = len(unit.status), len(unit.transitions)


def states(status: CellStatus) -> dict[str, str]:
    return {u.name: u.state_current_name for u in status.units if u.online}


@pytest.fixture
def plc(tmp_path: Path) -> Any:
    server = TestPlc(tmp_path, free_port())
    server.start()
    yield server
    server.close()


def hmi_unit(hmi: Bridge, unit: str) -> dict[str, Any]:
    """What the HMI's screens show of ``unit`` now."""
    shown: dict[str, Any] = hmi.snapshot()["units"][unit]
    return shown


def test_a_mixed_line_with_a_plc_unit_runs_faults_recovers_and_survives_the_plc_going_away(
    tmp_path: Path, ros: Any, processes: Processes, plc: TestPlc, request: pytest.FixtureRequest
) -> None:
    endpoint = f"opc.tcp://127.0.0.1:{plc.options['port']}"
    sim = {"durations": FAST, "cycle_time": 0.1, "faults": {"empty": {"kind": "starved"}}}
    path, cell = write_cell(
        tmp_path,
        {
            "robot": {"remote_commands_enabled": True,
                      "equipment_modules": {"gripper": {"sim": sim}}},
            "wrapper": {"remote_commands_enabled": True, "description": "wrapper (PLC)",
                        "plc": {"endpoint": endpoint, "reconnect_min": 0.2, "reconnect_max": 1.0}},
        },
        coordinator={
            "unit_lease": LEASE, "start_order": ["wrapper", "robot"],
            "interlocks": [{"unit": "wrapper", "when": "blocked", "suspend": ["robot"]},
                           {"unit": "robot", "when": "starved", "suspend": ["wrapper"]}],
            "lost_unit_reaction": "stop",
        },
    )  # fmt: skip
    start_unit_process(processes, path, "robot")
    start_em_process(processes, path, "robot", "gripper")
    bridge = processes.module("plc_wrapper", PLC_MODULE, str(path), "wrapper")
    processes.module("coordinator", "packml_ros2.coordinator_node", str(path))
    robot, wrapper = UnitClient(ros, cell, "robot"), UnitClient(ros, cell, "wrapper")
    presence = Presence(ros.add(Node("presence_probe", namespace=f"/{cell}", context=ros.context)),
                        [f"/{cell}/wrapper"], LEASE)  # what the OPC UA server follows  # fmt: skip
    line = Line(ros, cell)
    episodes = ros.subscribe(LineEpisode, f"/{cell}/coordinator/line/episodes", qos.LINE_EPISODES)
    hmi = Bridge(load_cell(path), context=ros.context, lease=LEASE).spin_in_background()
    request.addfinalizer(hmi.close)
    robot.ready(30)
    wrapper.ready(30)
    first = wrapper.transitions.wait_for(lambda t: True, 10, "the first transition")
    assert first.trigger == TransitionEvent.TRIGGER_RESTART
    assert first.detail == f"connected to the PLC at {endpoint} PackMLObjects/wrapper"
    assert wrapper.status.last.equipment_modules[0].name == "plc"
    line.wait(lambda m: m.all_online and len(states(m)) == 2, "both units online")
    bag = tmp_path / "line_bag"
    recorder = subprocess.Popen([*PACKML, "record", cell, "--config", str(path), "-o", str(bag)], cwd=ROOT,
                                stderr=subprocess.PIPE, text=True)  # fmt: skip
    request.addfinalizer(lambda: recorder.poll() is None and recorder.kill())  # a failed test's too
    recording = Output(recorder)
    for unit in ("robot", "wrapper"):
        recording.wait_for(f"receiving /{cell}/{unit}")

    # -- the coordinator sequences the PLC unit like its own --------------------------------------------
    reset = line.command(Cmd.RESET)
    assert reset.accepted, reset.message
    assert "in order wrapper > robot" in reset.message
    t = wrapper.transitions.wait_for(lambda t: t.to_state_name == "IDLE", 5, "wrapper idle")
    assert (t.command, t.source, list(t.skipped_states)) in (
        (Cmd.RESET, "remote:coordinator", [15]),  # Resetting passed between two publishes
        (0, "plc", []),  # State Complete from Resetting
    )
    resetting = [x for x in wrapper.transitions.messages if x.command == Cmd.RESET]
    assert resetting and resetting[-1].source == "remote:coordinator"
    # a cell command is answered when the units took it: the robot may still be resetting
    line.wait(lambda m: states(m) == {"robot": "IDLE", "wrapper": "IDLE"}, "the line idle")
    start = line.command(Cmd.START)
    assert start.accepted, start.message
    line.wait(lambda m: states(m) == {"robot": "EXECUTE", "wrapper": "EXECUTE"}, "the line running")
    # one HMI shows the PLC unit like the ROS unit: present, its state, its rule book's reasons
    wait_until(lambda: all(hmi_unit(hmi, u)["online"] and (hmi_unit(hmi, u)["status"] or {}).get("state_name") == "EXECUTE"
                           for u in ("robot", "wrapper")), 10, 0.05, "the HMI showing both units running")  # fmt: skip
    # record (the ROS side) takes the PLC unit like any other; replay replays the ROS units
    recorder.send_signal(signal.SIGINT)
    assert "wrote" in recording.rest() and recorder.returncode == 0
    recorded = load(bag).units[f"/{cell}/wrapper"]
    assert [
        t.trigger for t in map(partial(deserialize_message, message_type=TransitionEvent),
                               recorded.outputs["transitions"])] >= [TransitionEvent.TRIGGER_COMMAND, TransitionEvent.TRIGGER_STATE_COMPLETE]  # fmt: skip
    replayed = packml("replay", str(bag))
    assert replayed.returncode == 0, replayed.stdout + replayed.stderr
    assert "match (robot:" in replayed.stdout and "wrapper" not in replayed.stdout

    # -- interlocks both ways ------------------------------------------------------------------------------
    from_now(robot, wrapper)
    plc.send(blocked=True)  # the PLC's own EquipmentBlocked
    robot.wait_state("SUSPENDED")
    assert line.unit(line.status.last, "wrapper").blocked
    from_now(robot)
    plc.send(blocked=False)
    robot.wait_state("EXECUTE")
    from_now(robot, wrapper)
    ros.call(SetBool, f"/{cell}/robot/gripper/fault/empty", SetBool.Request(data=True))
    # (an acting state of the PLC may pass between two publishes: then it is a skipped state)
    suspended = wrapper.transitions.wait_for(
        lambda t: t.to_state_name in ("SUSPENDING", "SUSPENDED"),
        10,
        "the PLC suspended by the interlock",
        wrapper._transitions_since,
    )
    assert (suspended.trigger, suspended.source) == (TransitionEvent.TRIGGER_INTERLOCK, "coordinator")  # fmt: skip
    assert suspended.detail == "robot starved"
    wrapper.wait_status(lambda m: m.state_current_name == "SUSPENDED", 5, "wrapper suspended")
    from_now(wrapper)
    ros.call(SetBool, f"/{cell}/robot/gripper/fault/empty", SetBool.Request(data=False))
    unsuspended = wrapper.transitions.wait_for(
        lambda t: t.to_state_name in ("UNSUSPENDING", "EXECUTE"),
        10,
        "unsuspended",
        wrapper._transitions_since,
    )
    assert (unsuspended.trigger, unsuspended.detail) == (TransitionEvent.TRIGGER_INTERLOCK, "interlock cleared")  # fmt: skip
    wrapper.wait_entered("EXECUTE")
    sent = [t.command for t in wrapper.transitions.messages if t.trigger == TransitionEvent.TRIGGER_INTERLOCK]  # fmt: skip
    assert sent == [Cmd.SUSPEND, Cmd.UNSUSPEND]  # each sent once
    # stop episodes (issue 19): the PLC unit blocked is the root cause of the robot's suspension;
    # the robot starved (upstream, nothing before it) is the root cause of the PLC's
    blocked = episodes.wait_for(lambda e: e.id == 1 and not e.open, 10, "episode 1 closed")
    assert (blocked.root_unit, blocked.bucket) == ("wrapper", "blocked"), blocked
    assert affected(blocked) == {("robot", "propagated")}, blocked
    starved = episodes.wait_for(lambda e: e.id == 2 and not e.open, 10, "episode 2 closed")
    assert (starved.root_unit, starved.bucket) == ("robot", "starved"), starved
    assert affected(starved) == {("robot", "starved"), ("wrapper", "propagated")}, starved
    assert next(d for d in starved.affected if d.unit == "wrapper").cause_unit == "robot"
    from_now(wrapper)
    line.mark()

    # -- a fault in the PLC: the line stops, the PLC unit's stop reason is visible --------------------
    plc.send(fault={"id": 3001, "message": "Film break", "category": 2})
    stop = wrapper.transitions.wait_for(lambda t: t.to_state_name in ("STOPPING", "STOPPED"), 5,
                                        "the PLC stopping", wrapper._transitions_since)  # fmt: skip
    assert (stop.trigger, stop.command, stop.source) == (TransitionEvent.TRIGGER_ALARM, Cmd.STOP, "alarm:3001")  # fmt: skip
    assert stop.detail == "Film break"  # as a unit's alarm: the message (the ID is in the source)
    status = wrapper.wait_status(lambda m: m.state_current_name == "STOPPED", 5, "wrapper stopped")
    assert (status.stop_reason_id, status.alarm_banner) == (3001, "3001/0 Film break")
    admin = wrapper.admin.wait_for(lambda a: a.stop_reason.id == 3001, 5, "the stop reason")
    assert admin.stop_reason.message == "Film break" and admin.stop_reason_extent == 1
    alarms = wrapper.alarms.wait_for(lambda a: a.banner, 5, "the PLC's alarm")
    assert alarms.alarms[0].id == 3001 and alarms.alarms[0].trigger
    cell_view = line.wait(lambda m: m.state_current_name == "STOPPED", "the line stopped")
    assert line.unit(cell_view, "wrapper").alarm_banner == "3001/0 Film break"
    assert line.unit(cell_view, "wrapper").health == "alarm"

    # -- recovery: refused by the PLC while its alarm is active, then reset and start -------------------
    from_now(robot)
    assert line.command(Cmd.STOP).accepted
    robot.wait_state("STOPPED")  # the cell's RESET checks every unit first: the robot settled
    refused = line.command(Cmd.RESET)
    assert not refused.accepted and refused.result == Result.COMMAND_NOT_ALLOWED
    assert "wrapper refused RESET: RESET refused by the PLC in STOPPED in PRODUCTION mode (BadInvalidState" in refused.message  # fmt: skip
    plc.send(clear=True)
    assert line.command(Cmd.RESET).accepted
    line.wait(lambda m: states(m) == {"robot": "IDLE", "wrapper": "IDLE"}, "the line idle again")
    assert line.command(Cmd.START).accepted
    line.wait(lambda m: states(m) == {"robot": "EXECUTE", "wrapper": "EXECUTE"}, "running again")
    # the PLC's fault stopped the line: its alarm is the root cause, the cell's Stop followed
    fault = episodes.wait_for(lambda e: e.id == 3 and not e.open, 10, "episode 3 closed")
    assert (fault.root_unit, fault.bucket, fault.reason, fault.source) == (
        "wrapper", "unplanned_stop", "alarm 3001: Film break", "alarm:3001"), fault  # fmt: skip
    assert fault.stop_reason_known and fault.stop_reason.id == 3001, fault
    assert affected(fault) == {("wrapper", "internal"), ("robot", "cell")}, fault

    # -- the PLC process dies: lost within the lease everywhere, the line reacts ------------------------
    from_now(robot, wrapper)
    line.mark()
    killed = time.monotonic()
    plc.kill()
    lost = line.wait(lambda m: m.lost_units == ["wrapper"], "the PLC unit lost", 2 * LEASE)
    detected = time.monotonic() - killed
    print(f"killed PLC: lost at the coordinator after {detected:.2f} s")
    assert detected <= LEASE, f"loss seen by the coordinator after {detected:.2f} s"
    assert "wrapper (the PLC of wrapper (opc.tcp://" in lost.detail
    wait_until(lambda: presence.seen(f"/{cell}/wrapper").present is False, LEASE, 0.05,
               "the wrapper's presence lost")  # fmt: skip
    wait_until(lambda: ros.node.count_publishers(f"/{cell}/wrapper/status") == 0, LEASE, 0.05,
               "the wrapper's status withdrawn")  # fmt: skip
    answer = wrapper.command(Cmd.STOP)
    assert answer.result == Result.UNIT_UNAVAILABLE and "is not reachable since" in answer.message
    # ... the HMI too: the PLC unit shown lost (its last state kept), an action on it refused at once
    wait_until(lambda: hmi_unit(hmi, "wrapper")["online"] is False, LEASE, 0.05, "the HMI's wrapper lost")  # fmt: skip
    assert hmi_unit(hmi, "wrapper")["presence"]["reason"]
    acted = hmi.act_sync("wrapper", "command", {"command": "stop"})
    assert acted["result_name"] == "UNIT_UNAVAILABLE" and "not reachable since" in acted["message"]
    stopped = robot.wait_entered("STOPPING")  # the coordinator's lost_unit_reaction
    assert (stopped.command, stopped.source) == (Cmd.STOP, "remote:coordinator")

    # -- ... and comes back: reconnected with back-off, the line starts again -------------------------
    line.mark()
    plc.start()
    back = wrapper.transitions.wait_for(
        lambda t: t.trigger == TransitionEvent.TRIGGER_RESTART and "back after" in t.detail,
        15, "the bridge reconnected",
    )  # fmt: skip
    assert "lost: the connection to the PLC closed" in back.detail
    line.wait(lambda m: m.all_online and not m.lost_units, "the PLC unit online again")
    wait_until(lambda: hmi_unit(hmi, "wrapper")["online"], LEASE, 0.05, "the HMI's wrapper back")
    assert presence.seen(f"/{cell}/wrapper").present
    robot.wait_state("STOPPED")
    assert line.command(Cmd.RESET).accepted
    line.wait(lambda m: states(m) == {"robot": "IDLE", "wrapper": "IDLE"}, "idle after the restart")
    assert line.command(Cmd.START).accepted
    line.wait(lambda m: states(m) == {"robot": "EXECUTE", "wrapper": "EXECUTE"}, "running after the restart")  # fmt: skip
    # the PLC lost: the root cause, the robot stopped by the coordinator's reaction to it
    gone = episodes.wait_for(lambda e: e.id == 4 and not e.open, 10, "episode 4 closed")
    assert (gone.root_unit, gone.bucket) == ("wrapper", "unplanned_stop"), gone
    assert "lost" in gone.reason and "PLC" in gone.reason, gone
    assert ("robot", "propagated") in affected(gone), gone
    assert next(d for d in gone.affected if d.unit == "robot").cause_unit == "wrapper"

    # -- a PLC that goes silent (frozen: no FIN, only silence): the lease decides ------------------------
    diagnostics = ros.subscribe(DiagnosticArray, "/diagnostics", qos.DIAGNOSTICS)
    line.mark()
    frozen = time.monotonic()
    plc.signal(signal.SIGSTOP)
    line.wait(lambda m: m.lost_units == ["wrapper"], "the frozen PLC lost", 3 * LEASE)
    detected = time.monotonic() - frozen
    print(f"frozen PLC: lost at the coordinator after {detected:.2f} s")
    assert detected <= LEASE + 0.5, f"silence seen after {detected:.2f} s"
    stale = diagnostics.wait_for(
        lambda d: any(s.name == "packml: wrapper" and s.level == DiagnosticStatus.STALE for s in d.status),
        5, "the STALE diagnostics",
    )  # fmt: skip
    assert "no sign of life from the PLC" in next(s.message for s in stale.status if s.name == "packml: wrapper")  # fmt: skip
    line.mark()
    plc.signal(signal.SIGCONT)
    line.wait(lambda m: m.all_online and not m.lost_units, "the thawed PLC online again", 15)
    assert bridge.running()


def test_the_bridge_drives_this_projects_own_opcua_face_with_a_secured_user_session(
    tmp_path: Path, ros: Any, processes: Processes
) -> None:
    port = free_port()
    remote_path, remote = write_cell(
        tmp_path,
        {"filler": {"remote_commands_enabled": True,  # the bridge is an OPC UA (remote) client
                    "alarms": [{"id": 201, "message": "Nozzle clogged", "category": 2}]}},
        coordinator={"enabled": False, "unit_lease": LEASE},
    )  # fmt: skip
    doc = yaml.safe_load(remote_path.read_text())
    doc["opcua"] = {"port": port, "users": {"operator": hash_password("op-secret-1", iterations=1000)},
                    "state_dir": str(tmp_path / "server_state")}  # fmt: skip
    remote_path.write_text(yaml.safe_dump(doc))
    line_dir = tmp_path / "line"
    line_dir.mkdir()
    line_path, line = write_cell(
        line_dir,
        {"filler": {"plc": {"endpoint": f"opc.tcp://127.0.0.1:{port}/", "user": "operator",
                            "password": "env:TEST_PLC_PASSWORD", "security_policy": "Basic256Sha256",
                            "state_dir": str(tmp_path / "bridge_state")}}},
        coordinator={"enabled": False, "unit_lease": LEASE},
    )  # fmt: skip
    start_unit_process(processes, remote_path, "filler")
    start_face(processes, remote_path)
    processes.module("plc_filler", PLC_MODULE, str(line_path), "filler",
                     env={**os.environ, "TEST_PLC_PASSWORD": "op-secret-1"})  # fmt: skip
    target = UnitClient(ros, remote, "filler")
    bridged = UnitClient(ros, line, "filler")
    target.ready()
    bridged.ready(30)
    assert bridged.status.last.state_current_name == "STOPPED"

    answer = bridged.command(Cmd.RESET)
    assert answer.accepted, answer.message
    assert (answer.state_current, answer.state_requested) in ((2, 4), (15, 4), (4, 4))
    seen = target.wait_entered("RESETTING")
    assert seen.source == "opcua:operator"  # the user of the bridge's session
    bridged.wait_state("IDLE")
    t = bridged.transitions.wait_for(lambda t: t.command == Cmd.RESET, 5, "the bridged RESET")
    assert t.source == "operator"
    # packml status shows it like any unit (its one EM is the PLC link)
    shown = packml("status", f"{line}/filler")
    assert shown.returncode == 0, shown.stdout + shown.stderr
    assert f"/{line}/filler: IDLE (4) in PRODUCTION (1)" in shown.stdout
    assert "plc          online, active" in shown.stdout

    # an alarm of the remote unit stops it; the bridge names it as the cause
    from_now(bridged)
    target.call(
        SetAlarm, "set_alarm", id=201, value=0, active=True, category=-1, source="operator:test"
    )
    stop = bridged.transitions.wait_for(lambda t: t.to_state_name in ("STOPPING", "STOPPED"), 5,
                                        "the stop", bridged._transitions_since)  # fmt: skip
    assert (stop.trigger, stop.command, stop.source) == (TransitionEvent.TRIGGER_ALARM, Cmd.STOP, "alarm:201")  # fmt: skip
    bridged.wait_status(lambda m: m.state_current_name == "STOPPED" and m.stop_reason_id == 201, 5, "stopped by 201")  # fmt: skip
    # the remote unit refuses RESET (its alarm is active): its reason comes through diagnostics
    refused = bridged.command(Cmd.RESET)
    assert not refused.accepted and refused.result == Result.COMMAND_NOT_ALLOWED
    assert refused.message.startswith("RESET refused by the PLC in STOPPED in PRODUCTION mode (BadInvalidState: RESET refused")  # fmt: skip
    assert 'alarm 201/0 "Nozzle clogged" (category 2) with reaction STOP is still active' in refused.message  # fmt: skip
    target.call(
        SetAlarm, "set_alarm", id=201, value=0, active=False, category=-1, source="operator:test"
    )
    assert bridged.command(Cmd.RESET).accepted
    bridged.wait_state("IDLE")
