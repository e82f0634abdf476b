"""Issue 29 item 2: a cell behind a Fast DDS Discovery Server that `packml launch` hosts (the cell
file's ``discovery:`` block). Its nodes are the server's clients; `packml status`, `cmd`, `watch` and
the HMI are super clients and see the cell with ROS_DISCOVERY_SERVER set; simple discovery does not
(the cell really uses the server). Real processes: the launcher, the server, the CLI, the HMI."""

from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
import yaml

from packml_ros2.discovery_server import DiscoveryServerError, HostedServer
from test.ros.test_launcher_cli import FAST, Launched

pytestmark = pytest.mark.ros

PACKML = [sys.executable, "-m", "packml_ros2.cli.main"]


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def packml(env: dict[str, str], *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*PACKML, *args], capture_output=True, text=True, timeout=60, env=env,
                          check=False)  # fmt: skip


def test_a_cell_behind_the_discovery_server_it_hosts(tmp_path: Path, ros_domain: int) -> None:
    port = free_udp_port()
    name = f"ds{os.getpid()}"
    doc = {
        "cell": name,
        "defaults": {"remote_commands_enabled": True},
        "units": {"filler": {"persistence": False,
                             "equipment_modules": {"nozzle": {"sim": {"durations": FAST}}}}},
        "discovery": {"domain": ros_domain, "server": f"127.0.0.1:{port}", "host_server": True},
        "hmi": {"port": 0},
    }  # fmt: skip
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(doc))
    # the launcher is given no discovery variable: the cell file names the server
    base = {k: v for k, v in os.environ.items() if not k.startswith(("ROS_DISCOVERY", "ROS_SUPER"))}
    os.environ.pop("ROS_DISCOVERY_SERVER", None)
    launch = Launched([str(path), "--hmi"], tmp_path / "launch.log")
    try:
        up = launch.wait_ready(90)
        assert f"Discovery server on 127.0.0.1:{port}" in up, up
        client = {**base, "ROS_DISCOVERY_SERVER": f"127.0.0.1:{port}"}
        status = packml(client, "status", "--cell", name, "--timeout", "20")
        assert status.returncode == 0, status.stdout + status.stderr
        assert "filler" in status.stdout and "STOPPED" in status.stdout, status.stdout
        reset = packml(client, "cmd", "filler", "reset", "--cell", name, "--timeout", "20")
        assert reset.returncode == 0, reset.stdout + reset.stderr
        watch = packml(client, "watch", "--cell", name, "--frames", "1", "--plain", "--timeout", "20")  # fmt: skip
        assert watch.returncode == 0 and "filler" in watch.stdout, watch.stdout + watch.stderr
        # the HMI (a child of the launcher, a super client) sees the unit through the server
        url = re.search(r"(http://127\.0\.0\.1:\d+/)", launch.output())
        assert url is not None, launch.output()
        deadline = time.monotonic() + 30
        while True:
            units = httpx.get(f"{url.group(1)}api/snapshot", timeout=10).json()["units"]
            if units.get("filler", {}).get("status", {}).get("state_name") == "IDLE":
                break
            assert time.monotonic() < deadline, units
            time.sleep(0.1)
        # simple discovery in the same domain finds no unit of the cell
        blind = packml(base, "status", "--cell", name, "--timeout", "3")
        assert blind.returncode != 0 and "filler" not in blind.stdout, blind.stdout + blind.stderr
    finally:
        code = launch.ctrl_c()
    assert code == 0, launch.output()
    # the server ended with the cell: its port is free again
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", port))


def test_a_port_taken_is_said_and_nothing_starts(tmp_path: Path) -> None:
    first = HostedServer("127.0.0.1", free_udp_port())
    try:
        port = int(first.address.rsplit(":", 1)[1])
        with pytest.raises(DiscoveryServerError, match="did not start"):
            HostedServer("127.0.0.1", port, timeout=10)
        doc = {"cell": "taken", "units": {"u": {"persistence": False}},
               "discovery": {"server": f"127.0.0.1:{port}", "host_server": True}}  # fmt: skip
        path = tmp_path / "cell.yaml"
        path.write_text(yaml.safe_dump(doc))
        result = packml(dict(os.environ), "launch", str(path))
        assert result.returncode == 2, result.stdout + result.stderr
        assert "did not start" in result.stderr and "Traceback" not in result.stderr
        assert "is up" not in result.stdout
    finally:
        first.stop()
