"""Issue 29, a line of cells: each cell in its own ROS domain with its own coordinator, served
as one PackML object on its OPC 30050 face (``opcua.cell_object``); the line is a cell file whose
units are those objects (``plc:`` blocks, one PLC bridge each), sequenced by an ordinary
coordinator in the line's domain. No DDS between the cells and the line: OPC UA over TCP, as a
plant connects machines.

The line resets and starts the cells in its order; a fault of a unit inside one cell stops that
cell and the line's stop episode names the cell and its unit; a cell's face killed is a lost
cell within the lease (the line's lost-unit reaction stops the other cell), and it comes back
by itself when the face is restarted. Every wait is on a condition; everything listens on
127.0.0.1 (the namespace variant: ``test/ros/test_multihost.py`` style, issue 29's plant bench).
"""

from __future__ import annotations

import os
import signal
from pathlib import Path
from typing import Any

import pytest
import yaml
from packml_interfaces.msg import LineEpisode, Result
from packml_interfaces.srv import SetMachSpeed
from std_srvs.srv import SetBool

from packml_ros2 import qos
from packml_ros2.core import Cmd
from packml_ros2.opcua.config import hash_password
from packml_ros2.testing.environment import allocate_domain
from packml_ros2.testing.harness import RosHarness
from packml_ros2.testing.processes import NodeProcess, Processes, wait_until
from test.opcua.test_opcua import CLIENT_DIR, free_port, start_face
from test.plc.test_plc_line import LEASE, PLC_MODULE, Line, states
from test.ros.cells import UnitClient, start_em_process, start_unit_process, write_cell

pytestmark = pytest.mark.ros

FAST = {"resetting": 0.1, "starting": 0.1, "stopping": 0.1, "clearing": 0.1, "aborting": 0.05}
PASSWORD = "line-secret-1"

if not (CLIENT_DIR / "node_modules").is_dir():
    pytest.skip("the OPC UA test client is not installed: run tools/setup.sh --test", allow_module_level=True)  # fmt: skip


class Cell:
    """One cell: a unit ``robot`` with a simulated EM, its coordinator and its OPC UA face with
    the cell object, in a domain of its own."""

    def __init__(self, tmp_path: Path, processes: Processes, label: str, starting: float = 0.1) -> None:  # fmt: skip
        self.dir = tmp_path / label
        self.dir.mkdir()
        self.domain = allocate_domain()
        self.port = free_port()
        sim = {"durations": {**FAST, "starting": starting}, "cycle_time": 0.1, "faults": {"jam": {"kind": "alarm", "alarm_id": 301}}}  # fmt: skip
        self.path, self.name = write_cell(
            self.dir,
            {"robot": {"remote_commands_enabled": True,
                       "alarms": [{"id": 301, "message": "Gripper jammed", "category": 2}],
                       "equipment_modules": {"gripper": {"sim": sim}}}},
            coordinator={"unit_lease": LEASE},
        )  # fmt: skip
        doc = yaml.safe_load(self.path.read_text())
        doc["discovery"] = {"domain": self.domain}
        doc["opcua"] = {"port": self.port, "cell_object": True,
                        "users": {"line": hash_password(PASSWORD, iterations=1000)},
                        "state_dir": str(self.dir / "server_state")}  # fmt: skip
        self.path.write_text(yaml.safe_dump(doc))
        self.processes = processes
        start_unit_process(processes, self.path, "robot")
        start_em_process(processes, self.path, "robot", "gripper")
        self.label = label
        self.coordinator = self.start_coordinator()
        self.face = self.start_face()

    def start_coordinator(self) -> NodeProcess:
        return self.processes.module(
            f"coordinator_{self.label}", "packml_ros2.coordinator_node", str(self.path)
        )

    def start_face(self) -> NodeProcess:
        return start_face(self.processes, self.path, f"opcua_{self.name}")

    def plc(self, state_dir: Path) -> dict[str, Any]:
        """The line's ``plc:`` block for this cell's object."""
        return plc_block(f"127.0.0.1:{self.port}", self.name, "env:LINE_PLC_PASSWORD", state_dir)


def plc_block(address: str, cell: str, password: str, state_dir: Path) -> dict[str, Any]:
    """A line's ``plc:`` block for the object of ``cell`` served at ``address`` (host:port)."""
    return {"endpoint": f"opc.tcp://{address}/", "browse_path": f"PackMLObjects/{cell}",
            "user": "line", "password": password, "security_policy": "Basic256Sha256",
            "state_dir": str(state_dir), "reconnect_min": 0.2, "reconnect_max": 1.0}  # fmt: skip


def test_a_line_of_two_cells_over_their_opcua_faces(tmp_path: Path, ros: Any, processes: Processes) -> None:  # fmt: skip
    # cell a starts slower than the bridges' lease: its cell command (one OPC UA call) outlasts it
    a, b = Cell(tmp_path, processes, "a", starting=LEASE + 0.5), Cell(tmp_path, processes, "b")
    assert len({a.domain, b.domain, int(os.environ["ROS_DOMAIN_ID"])}) == 3
    line_dir = tmp_path / "line"
    line_dir.mkdir()
    line_path, line_name = write_cell(
        line_dir,
        {"cell_a": {"remote_commands_enabled": True, "plc": a.plc(tmp_path / "bridge_a")},
         "cell_b": {"remote_commands_enabled": True, "plc": b.plc(tmp_path / "bridge_b")}},
        coordinator={"unit_lease": LEASE, "start_order": ["cell_a", "cell_b"],
                     "lost_unit_reaction": "stop"},
    )  # fmt: skip
    env = {**os.environ, "LINE_PLC_PASSWORD": PASSWORD}
    for unit in ("cell_a", "cell_b"):
        processes.module(f"plc_{unit}", PLC_MODULE, str(line_path), unit, env=env)
    processes.module("line_coordinator", "packml_ros2.coordinator_node", str(line_path))
    line = Line(ros, line_name)
    episodes = ros.subscribe(LineEpisode, f"/{line_name}/coordinator/line/episodes", qos.LINE_EPISODES)  # fmt: skip
    cell_a, cell_b = UnitClient(ros, line_name, "cell_a"), UnitClient(ros, line_name, "cell_b")
    cell_a.ready(60)
    cell_b.ready(60)
    line.wait(lambda m: m.all_online and len(states(m)) == 2, "both cells online in the line", 30)
    assert cell_a.status.last.state_current_name == "STOPPED"

    # the cells' own domains: the test looks inside them only to cause a fault
    inside_b = RosHarness(b.domain)
    try:
        _run(line, episodes, cell_a, cell_b, a, b, inside_b)
    finally:
        inside_b.close()


def _run(line: Line, episodes: Any, cell_a: UnitClient, cell_b: UnitClient, a: Cell, b: Cell,
         inside_b: RosHarness) -> None:  # fmt: skip
    # -- the line resets and starts the cells in its order -------------------------------------------
    reset = line.command(Cmd.RESET)
    assert reset.accepted, reset.message
    assert "in order cell_a > cell_b" in reset.message
    line.wait(lambda m: states(m) == {"cell_a": "IDLE", "cell_b": "IDLE"}, "the cells idle", 30)
    line.mark()
    start = line.command(Cmd.START)
    assert start.accepted, start.message
    line.wait(lambda m: states(m) == {"cell_a": "EXECUTE", "cell_b": "EXECUTE"}, "the cells running", 30)  # fmt: skip
    # the PLC bridge counts a call in flight as the server busy for it, not as silence
    assert not [m.lost_units for m in line.status.messages[line._since :] if m.lost_units]
    a_run = cell_a.transitions.wait_for(lambda t: t.to_state_name == "EXECUTE", 5, "cell_a running")
    b_start = cell_b.transitions.wait_for(lambda t: t.to_state_name in ("STARTING", "EXECUTE"), 5, "cell_b starting")  # fmt: skip
    assert (a_run.stamp.sec, a_run.stamp.nanosec) <= (b_start.stamp.sec, b_start.stamp.nanosec)
    assert a_run.source in ("remote:coordinator", "plc")  # the line's command, or State Complete

    # -- what a cell has no one value for is refused, with the face's reason ------------------------
    speed = cell_a.call(SetMachSpeed, "set_mach_speed", mach_speed=10.0, source="operator")
    assert not speed.accepted and speed.result == Result.NOT_SUPPORTED, speed.message
    assert "not a cell command" in speed.message

    # -- a unit inside cell b faults: cell b stops, the line's episode names the cell and its unit --
    line.mark()
    inside_b.call(SetBool, f"/{b.name}/robot/gripper/fault/jam", SetBool.Request(data=True), 20)
    line.wait(lambda m: states(m).get("cell_b") in ("STOPPING", "STOPPED", "ABORTING", "ABORTED"),
              "cell_b stopped by its robot", 20)  # fmt: skip
    episode = episodes.wait_for(lambda e: e.root_unit == "cell_b", 20, "the line's stop episode")
    stopped = episodes.wait_for(lambda e: e.root_unit == "cell_b" and e.stop_reason_known, 20,
                                "the episode with cell_b's stop reason")  # fmt: skip
    assert (stopped.source, stopped.stop_reason.id) == ("alarm:301", 301)
    assert stopped.stop_reason.message == "robot: Gripper jammed"  # the cell's unit and its alarm
    assert episode.id == stopped.id
    assert states(line.status.last)["cell_a"] == "EXECUTE"  # one cell's stop is that cell's

    # -- line commands are all or nothing across cells; the refusal names the cell ------------------
    inside_b.call(SetBool, f"/{b.name}/robot/gripper/fault/jam", SetBool.Request(data=False), 20)
    refused = line.command(Cmd.RESET)
    assert not refused.accepted and "cell_a" in refused.message, refused.message
    assert line.command(Cmd.STOP).accepted
    line.wait(lambda m: states(m) == {"cell_a": "STOPPED", "cell_b": "STOPPED"}, "the cells stopped", 30)  # fmt: skip
    assert line.command(Cmd.RESET).accepted
    line.wait(lambda m: states(m) == {"cell_a": "IDLE", "cell_b": "IDLE"}, "the cells idle", 30)
    assert line.command(Cmd.START).accepted
    line.wait(lambda m: states(m) == {"cell_a": "EXECUTE", "cell_b": "EXECUTE"}, "running again", 30)  # fmt: skip

    # -- a cell whose face is gone is a lost unit of the line: the other cell stops -------------------
    line.mark()
    a.face.kill()
    line.wait(lambda m: "cell_a" in m.lost_units, "cell_a lost", LEASE + 10)
    line.wait(lambda m: states(m).get("cell_b") in ("STOPPING", "STOPPED"), "cell_b stopped by the line", 15)  # fmt: skip
    # a came back by itself once its face is there again
    a.face = a.start_face()
    line.wait(lambda m: m.all_online and not m.lost_units, "cell_a back", 30)
    wait_until(lambda: cell_a.status.last is not None and cell_a.status.last.state_current_name == "EXECUTE",
               10, 0.05, "cell_a still running behind its face")  # fmt: skip

    # -- a face whose coordinator is gone does not know the cell's state: the cell is lost too --------
    line.mark()
    b.coordinator.kill()
    lost = line.wait(lambda m: "cell_b" in m.lost_units, "cell_b lost with its coordinator", LEASE + 10)  # fmt: skip
    assert "no usable " in lost.detail and "(BadCommunicationError)" in lost.detail, lost.detail
    b.coordinator = b.start_coordinator()
    line.wait(lambda m: m.all_online and not m.lost_units, "cell_b back", 30)
    assert states(line.status.last)["cell_b"] == "STOPPED"


# ====================================================================================================
# Across hosts: each cell on a host of its own (a network namespace), the line on a third
# ====================================================================================================
NS_HOSTS = ("cella", "cellb", "line", "obs")  # "obs": test.ros.test_multihost's observer


@pytest.fixture
def hosts() -> Any:
    from packml_ros2.testing.netns import private_network

    with private_network(NS_HOSTS, "10.214.0", prefix="lc") as net:
        yield net


def _cell_doc(tmp_path: Path, label: str, address: str, domain: int) -> dict[str, Any]:
    (tmp_path / label).mkdir()
    sim = {"durations": FAST, "cycle_time": 0.1}
    return {
        "cell": f"lc{os.getpid() % 100000}{label}",
        "discovery": {"domain": domain},
        "units": {"robot": {"remote_commands_enabled": True,
                            "persistence": {"path": str(tmp_path / label / "{unit}.sqlite3")},
                            "equipment_modules": {"gripper": {"sim": sim}}}},
        "coordinator": {"unit_lease": LEASE},
        "opcua": {"host": address, "port": 4840, "cell_object": True,
                  "users": {"line": hash_password(PASSWORD, iterations=1000)},
                  "state_dir": str(tmp_path / f"{label}_server_state")},
    }  # fmt: skip


@pytest.mark.netns
def test_a_line_of_cells_on_three_hosts_rides_through_a_cell_host_cut_off(hosts: Any, tmp_path: Path) -> None:  # fmt: skip
    from test.ros.test_multihost import HostProcess, Observer

    logs = tmp_path / "logs"
    logs.mkdir()
    secret = tmp_path / "line.pw"
    secret.write_text(PASSWORD)
    secret.chmod(0o600)
    started: list[Any] = []

    def start(host: str, name: str, module: str, *args: str) -> Any:
        proc = HostProcess(hosts, host, name, module, *args, log_dir=logs)
        started.append(proc)
        return proc

    cells: dict[str, str] = {}
    units: dict[str, Any] = {}
    for label, host in (("a", "cella"), ("b", "cellb")):
        doc = _cell_doc(tmp_path, label, hosts.address[host], 20 + ord(label) - ord("a"))
        path = tmp_path / label / "cell.yaml"  # (its line store beside its units' stores)
        path.write_text(yaml.safe_dump(doc, sort_keys=False))
        cells[label] = doc["cell"]
        units[f"cell_{label}"] = {
            "remote_commands_enabled": True,
            "plc": plc_block(f"{hosts.address[host]}:4840", doc["cell"], f"file:{secret}",
                             tmp_path / f"bridge_{label}"),
        }  # fmt: skip
        start(host, f"robot_{label}", "packml_ros2.unit_node", str(path), "robot")
        start(host, f"gripper_{label}", "packml_ros2.sim_em", str(path), "robot", "gripper")
        start(host, f"coordinator_{label}", "packml_ros2.coordinator_node", str(path))
        start(host, f"opcua_{label}", "packml_ros2.cli.main", "opcua", str(path))
    line_name = f"lc{os.getpid() % 100000}line"
    line_file = tmp_path / "line.yaml"
    line_file.write_text(yaml.safe_dump({
        "cell": line_name, "units": units,
        "coordinator": {"unit_lease": LEASE, "start_order": ["cell_a", "cell_b"],
                        "lost_unit_reaction": "stop"},
    }, sort_keys=False))  # fmt: skip
    observer = Observer(hosts, line_name, ["cell_a", "cell_b"], logs)
    started.append(observer)
    try:
        for unit in ("cell_a", "cell_b"):
            start("line", f"plc_{unit}", PLC_MODULE, str(line_file), unit)
        coordinator = start("line", "line_coordinator", "packml_ros2.coordinator_node", str(line_file))  # fmt: skip

        def cell_states(c: dict[str, Any]) -> dict[str, str]:
            return {u["name"]: u["state_current_name"] for u in c["units"] if u["online"]}

        observer.wait_cell(lambda c: c["all_online"] and cell_states(c) == {"cell_a": "STOPPED", "cell_b": "STOPPED"},
                           60, "both cells online")  # fmt: skip
        for verb, settled in (("reset", "IDLE"), ("start", "EXECUTE")):
            answer = observer.ask("trigger", name=verb)
            assert answer["success"], answer["message"]
            observer.wait_cell(lambda c, s=settled: cell_states(c) == {"cell_a": s, "cell_b": s},
                               20, f"both cells in {settled}")  # fmt: skip

        # -- cell a's host cut off: the line loses cell a within its lease, stops cell b -------------
        hosts.cut("cella")
        lost = observer.wait_cell(lambda c: c["lost_units"] == ["cell_a"], LEASE + 5, "cell_a lost")
        assert not lost["all_online"]
        observer.wait_cell(lambda c: cell_states(c).get("cell_b") == "STOPPED", 15, "cell_b stopped by the line")  # fmt: skip

        # -- back: the bridge reconnects by itself; cell a ran on alone (nothing of it was cut) ------
        hosts.restore("cella")
        back = observer.wait_cell(
            lambda c: c["all_online"] and not c["lost_units"], 30, "cell_a back"
        )
        assert cell_states(back)["cell_a"] == "EXECUTE"
        for verb, settled in (("stop", "STOPPED"), ("reset", "IDLE"), ("start", "EXECUTE")):
            answer = observer.ask("trigger", name=verb)
            assert answer["success"], f"{verb}: {answer['message']}"
            observer.wait_cell(lambda c, s=settled: cell_states(c) == {"cell_a": s, "cell_b": s},
                               20, f"both cells in {settled} again")  # fmt: skip
        assert "unit cell_a lost" in coordinator.output()
    finally:
        failures = []
        for proc in reversed(started):  # the line first, then the cells
            code = proc.stop()
            if code not in (0, -signal.SIGINT, -signal.SIGKILL, -signal.SIGTERM):
                failures.append(f"--- {proc.name} exited {code} ---\n{proc.output()[-2000:]}")
        if failures:
            print("\n".join(failures))
