"""Issue 29 item 2: the real ``ros2`` CLI commands a cell that runs behind the Discovery Server
`packml launch` hosts, as a super client (ROS_DISCOVERY_SERVER and ROS_SUPER_CLIENT), and the same
command without the server finds nothing."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest
import yaml

from .tools import Background, require, ros2_daemon, shell

pytestmark = [pytest.mark.ros, pytest.mark.slow]


def test_ros2_service_call_through_the_discovery_server(tmp_path: Path, ros_domain: int) -> None:
    require("ros2")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])
    doc = {"cell": "ds_cell", "units": {"filler": {"persistence": False}},
           "discovery": {"domain": ros_domain, "server": f"127.0.0.1:{port}", "host_server": True}}  # fmt: skip
    (tmp_path / "cell.yaml").write_text(yaml.safe_dump(doc))
    cell = Background("exec packml launch cell.yaml", tmp_path, tmp_path, tmp_path / "launch.log")
    try:
        cell.wait_for("is up", 90)
        with ros2_daemon(tmp_path):
            called = shell(
                f"ROS_DISCOVERY_SERVER=127.0.0.1:{port} ROS_SUPER_CLIENT=TRUE "
                "ros2 service call /ds_cell/filler/reset std_srvs/srv/Trigger",
                tmp_path, tmp_path, timeout=60,
            )  # fmt: skip
            assert called.returncode == 0, called.stdout
            assert "success=True" in called.stdout, called.stdout
            listed = shell("ros2 node list --no-daemon", tmp_path, tmp_path, timeout=60)
            assert "/ds_cell/filler" not in listed.stdout, listed.stdout  # simple discovery: blind
    finally:
        code = cell.ctrl_c()
    assert code == 0, cell.output()
