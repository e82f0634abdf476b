"""A service's answer waits for a new client to be discovered instead of being dropped.

rmw_fastrtps sends a service's (and an action's) answer only once the server has discovered the
client's response reader, and waits for it as long as the response writer's reliability
``max_blocking_time`` (Fast DDS's default: 100 ms). On a loaded host the request can arrive
before that reader is discovered, the answer is dropped, and the client (an EM's goal, an
operator's ``packml cmd``) waits for an answer that never comes. Every profile packml_ros2
selects sets it for services (the ``service`` data-writer profile) to 1 s, and Fast DDS loads it
without a parse error.
"""

from __future__ import annotations

import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from packml_ros2 import dds_profile
from packml_ros2.paths import config_dir

NS = {"d": "http://www.eprosima.com"}
CALL = """
import rclpy
from rclpy.node import Node
from rclpy.executors import SingleThreadedExecutor
from std_srvs.srv import SetBool
rclpy.init()
server, client = Node("server"), Node("client")
server.create_service(SetBool, "s", lambda req, res: (setattr(res, "success", req.data), res)[1])
executor = SingleThreadedExecutor()
executor.add_node(server)
executor.add_node(client)
c = client.create_client(SetBool, "s")
assert c.wait_for_service(timeout_sec=30)
future = c.call_async(SetBool.Request(data=True))
executor.spin_until_future_complete(future, 30)
print("answered", future.result().success, flush=True)
"""


def _profiles(tmp_path: Path) -> list[Path]:
    written = tmp_path / "interfaces.xml"
    written.write_text(dds_profile.profile_xml(["127.0.0.1"]), encoding="utf-8")
    return [config_dir() / "fastdds_loopback.xml", config_dir() / "fastdds_localhost.xml", written]


def test_every_profile_lets_a_service_wait_a_second_for_its_client(tmp_path: Path) -> None:
    for path in _profiles(tmp_path):
        writers = ET.parse(path).getroot().findall("d:profiles/d:data_writer", NS)
        service = [w for w in writers if w.get("profile_name") == "service"]
        assert len(service) == 1, path
        wait = service[0].find("d:qos/d:reliability/d:max_blocking_time", NS)
        assert wait is not None, path
        seconds = int(wait.findtext("d:sec", "0", NS)) + int(wait.findtext("d:nanosec", "0", NS)) / 1e9  # fmt: skip
        assert seconds >= 1.0, (path, seconds)


@pytest.mark.parametrize("which", [0, 1, 2], ids=["loopback", "localhost", "interfaces"])
def test_fast_dds_loads_the_profile_and_a_service_answers(tmp_path: Path, ros_domain: int, which: int) -> None:  # fmt: skip
    path = _profiles(tmp_path)[which]
    env = dict(os.environ, FASTDDS_DEFAULT_PROFILES_FILE=str(path), ROS_DOMAIN_ID=str(ros_domain),
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")  # fmt: skip
    done = subprocess.run([sys.executable, "-c", CALL], check=False, env=env, capture_output=True, text=True, timeout=90)  # fmt: skip
    assert "answered True" in done.stdout, done.stderr[-2000:]
    assert "XMLPARSER" not in done.stderr and "Error" not in done.stderr, done.stderr[-2000:]
