"""Issue 25 item 4: a cell meant to be local cannot be reached from another host.

The unit runs in one network namespace ("host") with the environment packml_ros2 makes by default
(ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, no profile chosen by the user: run.py selects
config/fastdds_loopback.xml). A process in a second namespace that names the first one's address
as a static peer (ROS_STATIC_PEERS) must not discover its services; a process on the unit's own
host does (the positive control). Before, the remote process discovered the unit in 0.2 s and
commanded it: the discovery range alone left every socket listening on 0.0.0.0."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from test.ros.test_multihost import REPO, Network, network  # noqa: F401


def _probe(net: Network, host: str, env: dict[str, str], service: str, timeout: float) -> str:
    """Run this file's probe in ``host``: FOUND or NOTFOUND (within ``timeout`` s)."""
    done = subprocess.run(
        [*net.exec_args(host), sys.executable, "-m", "test.ros.test_local_only", service, str(timeout)],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout + 30, check=False,
    )  # fmt: skip
    return done.stdout.strip() or f"no answer: {done.stderr[-2000:]}"


@pytest.mark.netns
@pytest.mark.ros
def test_a_local_cell_is_not_reachable_from_another_host(network: Network, tmp_path: Path) -> None:  # noqa: F811
    cell_file = tmp_path / "cell.yaml"
    cell = f"lo{os.getpid() % 100000}"
    cell_file.write_text(yaml.safe_dump({"cell": cell, "units": {"u": {}}}))
    base = dict(os.environ, PYTHONUNBUFFERED="1",
                PYTHONPATH=os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH", "")) if p))  # fmt: skip
    for name in ("FASTDDS_DEFAULT_PROFILES_FILE", "FASTDDS_BUILTIN_TRANSPORTS", "ROS_STATIC_PEERS"):
        base.pop(name, None)  # packml_ros2's own choice, as a user's shell would have it
    local = dict(base, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    remote = dict(base, ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET", ROS_STATIC_PEERS=network.address["units"])  # fmt: skip
    log = (tmp_path / "unit.log").open("wb")
    unit = subprocess.Popen(
        [*network.exec_args("units"), sys.executable, "-m", "packml_ros2.unit_node", str(cell_file), "u"],
        cwd=REPO, env=local, stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
    )  # fmt: skip
    try:
        service = f"/{cell}/u/command"
        assert _probe(network, "units", local, service, 20) == "FOUND"  # on its own host
        assert _probe(network, "obs", remote, service, 8) == "NOTFOUND"  # from another host
        assert unit.poll() is None
    finally:
        unit.terminate()
        unit.wait(10)
        log.close()


def _main(service: str, timeout: float) -> None:
    import rclpy
    from packml_interfaces.srv import Command

    rclpy.init()
    node = rclpy.create_node("probe")
    client = node.create_client(Command, service)
    print("FOUND" if client.wait_for_service(timeout_sec=timeout) else "NOTFOUND", flush=True)
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == "__main__":
    _main(sys.argv[1], float(sys.argv[2]))
