"""A cell spread over several "hosts": network namespaces the test creates itself.

Topology (all private, nothing reaches the machine's own interfaces): a bridge namespace ``br``
and one namespace per host, each joined to the bridge by a veth pair, on 10.213.0.0/24:

    units (10.213.0.1)  -- the unit processes
    ems   (10.213.0.2)  -- the simulated EM processes
    coord (10.213.0.3)  -- the cell coordinator
    obs   (10.213.0.4)  -- the observer: this file run as ``python -m test.ros.test_multihost
                           observe ...``, answering the test's questions on stdin/stdout

Inside the namespaces DDS runs with ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET (the namespaces' subnet
is all there is) and FASTDDS_BUILTIN_TRANSPORTS=UDPv4 (shared memory would bypass the network and
cutting a link would change nothing). The scenario: the cell runs; the units' link is cut -> each
unit loses its EMs and reacts as configured (filler aborts, capper stops), the coordinator reports
both units lost; the link comes back -> EMs and units re-join, and the cell is cleared, reset and
started again through the coordinator.

Skipped (with the reason) where namespaces cannot be created. The namespaces and every process
started in them are removed at teardown, also when the test fails.
"""

from __future__ import annotations

import json
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from packml_ros2.testing.netns import Network, NsProcess, private_network

REPO = Path(__file__).resolve().parents[2]
SUBNET = "10.213.0"
HOSTS = ("units", "ems", "coord", "obs")


# ====================================================================================================
# Network namespaces
# ====================================================================================================
@pytest.fixture
def network() -> Iterator[Network]:
    with private_network(HOSTS, SUBNET) as net:
        yield net


# ====================================================================================================
# Processes inside namespaces
# ====================================================================================================
def _ns_environment() -> dict[str, str]:
    from packml_ros2.paths import fastdds_profile

    env = dict(os.environ)
    env.update(
        ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET",  # only the namespaces' own subnet exists in there
        FASTDDS_BUILTIN_TRANSPORTS="UDPv4",  # no shared memory across "hosts"
        FASTDDS_DEFAULT_PROFILES_FILE=str(fastdds_profile()),
        PYTHONUNBUFFERED="1",
        PYTHONPATH=os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH", "")) if p),
    )
    return env


class HostProcess(NsProcess):
    """``python -m module args`` inside a host's namespace; output to ``log``."""

    def __init__(self, net: Network, host: str, name: str, module: str, *args: str,
                 log_dir: Path, pipe: bool = False) -> None:  # fmt: skip
        cmd = [sys.executable, "-m", module, *args]
        super().__init__(net, host, name, cmd, _ns_environment(), log_dir, pipe=pipe, cwd=REPO)


class Observer(HostProcess):
    """The observer process: one JSON request per line, one JSON answer per line (ask)."""

    def __init__(self, net: Network, cell: str, units: list[str], log_dir: Path) -> None:
        super().__init__(net, "obs", "observer", "test.ros.test_multihost", "observe", cell,
                         *units, log_dir=log_dir, pipe=True)  # fmt: skip

    def poll(self, ask: Callable[[], Any], timeout: float, what: str) -> Any:
        """Ask again (every 50 ms) until the answer is truthy."""
        deadline = time.monotonic() + timeout
        last = None
        while time.monotonic() < deadline:
            last = ask()
            if last:
                return last
            time.sleep(0.05)
        raise TimeoutError(f"no {what} within {timeout:g} s; last answer: {last}")

    def wait_cell(self, predicate: Callable[[dict[str, Any]], bool], timeout: float, what: str) -> dict[str, Any]:  # fmt: skip
        """Poll the cell status the observer holds until ``predicate`` holds."""

        def ask() -> dict[str, Any] | None:
            cell = self.ask("cell")
            return cell if cell is not None and predicate(cell) else None

        return self.poll(ask, timeout, f"cell status with {what}")


# ====================================================================================================
# The scenario
# ====================================================================================================
EM_SIM = {"cycle_time": 0.2, "counter": "processed", "lease": 0.5,
          "durations": {"starting": 0.1, "stopping": 0.1, "aborting": 0.1}}  # fmt: skip


def _units(cell: dict[str, Any]) -> dict[str, dict[str, Any]]:
    return {u["name"]: u for u in cell["units"]}


@pytest.mark.netns
@pytest.mark.ros
def test_cell_rides_through_a_cut_network_link(network: Network, tmp_path: Path) -> None:
    import yaml

    cell = f"mh{os.getpid() % 100000}"
    doc = {
        "cell": cell,
        "defaults": {"remote_commands_enabled": True, "em_lease": 0.5,
                     "persistence": {"path": str(tmp_path / "{unit}.sqlite3")}},
        "units": {
            "filler": {"equipment_modules": {"doser": {"sim": EM_SIM}}},  # EM lost: abort (default)
            "capper": {"equipment_modules": {"screwer": {"sim": EM_SIM}}, "em_lost_reaction": "stop"},
        },
        "coordinator": {"start_order": ["capper", "filler"], "unit_lease": 2.0, "step_timeout": 10.0},
    }  # fmt: skip
    cell_file = tmp_path / "cell.yaml"
    cell_file.write_text(yaml.safe_dump(doc, sort_keys=False))
    logs = tmp_path / "logs"
    logs.mkdir()
    started: list[HostProcess] = []

    def start(host: str, name: str, module: str, *args: str) -> HostProcess:
        proc = HostProcess(network, host, name, module, *args, log_dir=logs)
        started.append(proc)
        return proc

    observer = Observer(network, cell, ["filler", "capper"], logs)
    started.append(observer)
    try:
        for unit in ("filler", "capper"):
            start("units", unit, "packml_ros2.unit_node", str(cell_file), unit)
        start("ems", "doser", "packml_ros2.sim_em", str(cell_file), "filler", "doser")
        start("ems", "screwer", "packml_ros2.sim_em", str(cell_file), "capper", "screwer")
        coordinator = start("coord", "coordinator", "packml_ros2.coordinator_node", str(cell_file))

        def every_em_online(c: dict[str, Any]) -> bool:
            return c["all_online"] and all(u["em_online"] == u["em_total"] == 1 for u in c["units"])

        observer.wait_cell(every_em_online, 20, "every unit and EM online")
        # a cell command is answered when the units took it; the next waits for them to settle
        for verb, settled in (("reset", "IDLE"), ("start", "EXECUTE")):
            answer = observer.ask("trigger", name=verb)
            assert answer["success"], answer["message"]
            observer.wait_cell(
                lambda c, s=settled: c["state_current_name"] == s, 10, f"cell in {settled}"
            )

        # -- cut the units' host off: the units lose their EMs, the coordinator loses the units
        cut_at = time.monotonic()
        network.cut("units")
        lost = observer.wait_cell(
            lambda c: c["lost_units"] == ["filler", "capper"], 2.0 + 2.0, "both units lost"
        )
        detected = time.monotonic() - cut_at
        assert detected <= 2.0 + 1.0, f"units reported lost after {detected:.2f} s"
        assert not lost["all_online"]
        assert {u["name"]: u["health"] for u in lost["units"]} == {"filler": "offline", "capper": "offline"}  # fmt: skip
        answer = observer.ask("trigger", name="stop")  # a cell command now ends at a lost unit
        assert not answer["success"] and "offline" in answer["message"]

        # -- restore: EMs and units re-join; the units tell what happened while they were cut off
        network.restore("units")
        back = observer.wait_cell(
            lambda c: every_em_online(c) and not c["lost_units"], 15, "everything re-joined"
        )
        units = _units(back)
        assert units["filler"]["state_current_name"] in ("ABORTING", "ABORTED")
        assert units["capper"]["state_current_name"] in ("STOPPING", "STOPPED")
        for unit, em, to in (("filler", "doser", "ABORTING"), ("capper", "screwer", "STOPPING")):
            # the observer was cut off from the units too: what it missed comes by reliable repair
            reactions = observer.poll(
                lambda unit=unit: [t for t in observer.ask("transitions", unit=unit)
                                   if t["trigger_name"] == "EM_LOST"],
                8, f"{unit}'s reaction to losing {em}",
            )  # fmt: skip
            assert reactions[-1]["from_state_name"] == "EXECUTE"
            assert reactions[-1]["to_state_name"] == to and em in reactions[-1]["detail"]
        observer.wait_cell(lambda c: c["state_current_name"] == "ABORTED", 5, "cell Aborted")

        # -- and the cell runs again, through the coordinator
        for verb, settled in (("clear", "STOPPED"), ("reset", "IDLE")):
            answer = observer.ask("trigger", name=verb)
            assert answer["success"], f"{verb}: {answer['message']}"
            observer.wait_cell(
                lambda c, s=settled: c["state_current_name"] == s, 10, f"cell in {settled}"
            )
        answer = observer.ask("trigger", name="start")
        assert answer["success"], f"start: {answer['message']}"
        running = observer.wait_cell(
            lambda c: c["state_current_name"] == "EXECUTE" and all(
                u["state_current_name"] == "EXECUTE" and u["health"] == "ok" for u in c["units"]
            ),
            5,
            "cell in Execute again",
        )  # fmt: skip
        assert running["all_online"] and not running["busy"]
        assert "unit filler lost" in coordinator.output()
        assert "unit filler online again" in coordinator.output()
    finally:
        failures = []
        # coordinator, units, EMs, observer: EMs that stop first would make the units react
        rank = {"coordinator": 0, "filler": 1, "capper": 1, "doser": 2, "screwer": 2}
        for proc in sorted(started, key=lambda p: rank.get(p.name, 3)):
            code = proc.stop()
            if code not in (0, -signal.SIGINT, -signal.SIGKILL):
                failures.append(f"--- {proc.name} exited {code} ---\n{proc.output()[-2000:]}")
        if failures:
            print("\n".join(failures))


# ====================================================================================================
# The observer process (runs inside the "obs" namespace)
# ====================================================================================================
def _to_data(value: Any) -> Any:
    if hasattr(value, "get_fields_and_field_types"):
        return {name: _to_data(getattr(value, name)) for name in value.get_fields_and_field_types()}
    if isinstance(value, (list, tuple)) or type(value).__name__ in ("array", "ndarray"):
        return [_to_data(v) for v in value]
    if isinstance(value, (bytes, bytearray)):
        return list(value)
    if hasattr(value, "item"):  # numpy scalars
        return value.item()
    return value


def _observe(cell: str, units: list[str]) -> int:
    import rclpy
    from rclpy.node import Node
    from std_srvs.srv import Trigger

    from packml_ros2 import run
    from packml_ros2.client import CellProxy
    from packml_ros2.executors import MultiThreadedExecutor, spin_in_thread

    run.default_environment()
    rclpy.init()
    node = Node(f"observer_{os.getpid()}")
    proxy = CellProxy(node, cell, units)
    executor = MultiThreadedExecutor(num_threads=4)
    thread = spin_in_thread(executor, node)
    clients: dict[str, Any] = {}

    def trigger(name: str, timeout: float = 20.0) -> dict[str, Any]:
        if name not in clients:
            clients[name] = node.create_client(Trigger, f"/{cell}/coordinator/{name}")
        client = clients[name]
        if not client.wait_for_service(timeout_sec=timeout):
            return {"success": False, "message": f"/{cell}/coordinator/{name} not available"}
        done = threading.Event()
        future = client.call_async(Trigger.Request())
        future.add_done_callback(lambda _: done.set())
        if not done.wait(timeout):
            return {"success": False, "message": f"no answer within {timeout:g} s"}
        resp = future.result()
        return {"success": resp.success, "message": resp.message}

    try:
        for line in sys.stdin:
            request = json.loads(line)
            op = request.pop("op")
            try:
                if op == "cell":
                    answer = _to_data(proxy.cell_status) if proxy.cell_status else None
                elif op == "unit":
                    status = proxy.unit(request["unit"]).status
                    answer = _to_data(status) if status else None
                elif op == "transitions":
                    answer = [_to_data(t) for t in list(proxy.unit(request["unit"]).transitions)]
                elif op == "trigger":
                    answer = trigger(request["name"], request.get("timeout", 20.0))
                else:
                    answer = {"error": f"unknown op {op!r}"}
            except Exception as exc:  # answer with the error, keep serving
                answer = {"error": repr(exc)}
            print(json.dumps(answer), flush=True)
    finally:
        executor.shutdown(timeout_sec=2)
        node.destroy_node()
        rclpy.try_shutdown()
        thread.join(2)
    return 0


if __name__ == "__main__":
    if len(sys.argv) >= 3 and sys.argv[1] == "observe":
        sys.exit(_observe(sys.argv[2], sys.argv[3:]))
    print("usage: python -m test.ros.test_multihost observe <cell> <unit>...", file=sys.stderr)
    sys.exit(2)
