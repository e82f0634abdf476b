"""Issue 25 item 4 (the rest): the cell file names the network interfaces DDS uses.

``dds.interfaces`` is validated with the cell file (names or IPv4 addresses, a key path in each
refusal) and applied by ``packml launch`` through a Fast DDS profile it writes. Across network
namespaces: a cell launched with ``interfaces: [eth0]`` and the SUBNET discovery range is reached
from another host (a static-peer probe finds its unit); the same cell with ``interfaces:
[127.0.0.1]`` is not, though the discovery range is SUBNET and a probe on its own host finds it.
Each namespace has its own machine id, as separate hosts do (:func:`own_machine_ids`).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
import yaml

from packml_ros2 import dds_profile
from packml_ros2.core import load_cell
from packml_ros2.core.config import parse_cell
from packml_ros2.core.schema import ConfigError
from packml_ros2.launcher import plan
from packml_ros2.testing.processes import wait_until
from test.ros.test_local_only import _probe
from test.ros.test_multihost import REPO, Network, network  # noqa: F401


def _doc(interfaces: Any) -> dict[str, Any]:
    return {"cell": "c", "units": {"u": {}}, "dds": {"interfaces": interfaces}}


def test_the_key_takes_interface_names_and_ipv4_addresses_and_refuses_the_rest() -> None:
    cell = parse_cell(_doc(["eth1", "192.168.10.5", "enp0s31f6", "eth1"]))
    assert cell.dds_interfaces == ("eth1", "192.168.10.5", "enp0s31f6")
    assert parse_cell({"cell": "c", "units": {"u": {}}}).dds_interfaces == ()
    with pytest.raises(ConfigError) as err:
        parse_cell({"cell": "c", "units": {"u": {}}, "dds": {
            "interfaces": ["eth0; rm -rf /", "::1", "224.0.0.1", "0.0.0.0", "x" * 16, 5.5, ["a"]],
            "transport": "udp"}})  # fmt: skip
    problems = dict(err.value.problems)
    assert "neither an interface name" in problems["dds.interfaces[0]"]
    for i in (1, 2, 3):
        assert "unicast IPv4 address" in problems[f"dds.interfaces[{i}]"], problems
    assert "neither an interface name" in problems["dds.interfaces[4]"]
    assert "expected a string" in problems["dds.interfaces[6]"]
    assert "unknown key" in problems["dds.transport"]
    with pytest.raises(ConfigError, match="name at least one interface"):
        parse_cell(_doc([]))


def test_the_profile_keeps_udp_on_the_named_interfaces_and_loopback(tmp_path: Path) -> None:
    xml = dds_profile.profile_xml(["eth1", "192.168.10.5"])
    assert (
        "<interfaceWhiteList><address>127.0.0.1</address><interface>eth1</interface>"
        "<address>192.168.10.5</address></interfaceWhiteList>" in xml
    )
    assert "<useBuiltinTransports>false</useBuiltinTransports>" in xml and "SHM" in xml
    assert dds_profile.on_this_host("lo") and dds_profile.on_this_host("127.0.0.1")
    assert not dds_profile.on_this_host("no-such-if0")
    assert not dds_profile.on_this_host("192.0.2.77")  # (TEST-NET-1: never an address here)
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump({**_doc(["no-such-if0", "192.0.2.77"]), "units": {"u": {
        "persistence": {"path": str(tmp_path / "{unit}.sqlite3")}}}}))  # fmt: skip
    with pytest.raises(ConfigError) as err:
        plan(path)  # packml launch refuses before anything starts
    assert "this host has none of no-such-if0, 192.0.2.77" in dict(err.value.problems)["dds.interfaces"]  # fmt: skip
    path.write_text(path.read_text().replace("no-such-if0", "lo"))
    cell = load_cell(path)
    before = os.environ.get("FASTDDS_DEFAULT_PROFILES_FILE")
    try:
        written = dds_profile.apply(cell)
        assert written == tmp_path / "fastdds_interfaces.xml"
        assert os.environ["FASTDDS_DEFAULT_PROFILES_FILE"] == str(written)
        assert "<interface>lo</interface>" in written.read_text()
        assert "192.0.2.77" not in written.read_text()  # (not on this host)
    finally:
        if before is None:
            os.environ.pop("FASTDDS_DEFAULT_PROFILES_FILE", None)
        else:
            os.environ["FASTDDS_DEFAULT_PROFILES_FILE"] = before


def _launch(net: Network, tmp_path: Path, name: str, interfaces: list[str], env: dict[str, str]) -> tuple[subprocess.Popen[bytes], Path]:  # fmt: skip
    folder = tmp_path / name
    folder.mkdir()
    cell_file = folder / "cell.yaml"
    cell_file.write_text(yaml.safe_dump({
        "cell": name, "dds": {"interfaces": interfaces},
        "units": {"u": {"persistence": {"path": str(folder / "{unit}.sqlite3")}}}}))  # fmt: skip
    log = folder / "launch.log"
    with log.open("wb") as out:
        launched = subprocess.Popen(
            [*net.exec_args("units"), sys.executable, "-m", "packml_ros2.cli.main", "launch", str(cell_file)],
            cwd=REPO, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True,
        )  # fmt: skip
    return launched, log


def _said(log: Path, launched: subprocess.Popen[bytes]) -> Any:
    return lambda: b"DDS on " in log.read_bytes() or launched.poll() is not None


@contextmanager
def own_machine_ids(net: Network) -> Iterator[None]:
    """Each namespace its own /etc/machine-id (``ip netns exec`` mounts /etc/netns/<ns>/ over
    /etc), as separate hosts have: Fast DDS takes participants with the same one for processes
    of one host and reaches them through its loopback, which a named interface leaves out."""
    made = []
    try:
        for ns in net.ns.values():
            folder = Path("/etc/netns") / ns
            folder.mkdir(parents=True, exist_ok=True)
            made.append(folder)
            (folder / "machine-id").write_text(uuid.uuid4().hex + "\n")
        yield
    finally:
        for folder in made:
            shutil.rmtree(folder, ignore_errors=True)
        with contextlib.suppress(OSError):
            Path("/etc/netns").rmdir()  # (only when no other test's namespace uses it)


def _stop(launched: subprocess.Popen[bytes]) -> None:
    launched.send_signal(signal.SIGINT)
    try:
        launched.wait(20)
    except subprocess.TimeoutExpired:
        launched.kill()
        launched.wait(10)


@pytest.mark.netns
@pytest.mark.ros
def test_a_named_interface_is_reached_from_another_host_and_loopback_is_not(
    network: Network,  # noqa: F811
    tmp_path: Path,
) -> None:
    base = dict(os.environ, PYTHONUNBUFFERED="1",
                PYTHONPATH=os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH", "")) if p))  # fmt: skip
    for name in ("FASTDDS_DEFAULT_PROFILES_FILE", "FASTDDS_BUILTIN_TRANSPORTS", "ROS_STATIC_PEERS"):
        base.pop(name, None)
    subnet = dict(base, ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET")  # a multi-host cell
    remote = dict(subnet, ROS_STATIC_PEERS=network.address["units"])
    tag = os.getpid() % 100000
    with own_machine_ids(network):
        _reached(network, tmp_path, tag, subnet, remote)


def _reached(network: Network, tmp_path: Path, tag: int, subnet: dict[str, str], remote: dict[str, str]) -> None:  # noqa: F811  # fmt: skip
    for name, interfaces, reached in ((f"ifa{tag}", ["eth0"], "FOUND"),
                                      (f"ifb{tag}", ["127.0.0.1"], "NOTFOUND")):  # fmt: skip
        launched, log = _launch(network, tmp_path, name, interfaces, subnet)
        try:
            wait_until(_said(log, launched), 60, what="the launcher's DDS line")
            assert f"DDS on {interfaces[0]}, 127.0.0.1 and shared memory only" in log.read_text()
            service = f"/{name}/u/command"
            assert _probe(network, "units", subnet, service, 30) == "FOUND"  # on its own host
            assert _probe(network, "obs", remote, service, 8) == reached, (name, interfaces)
            assert launched.poll() is None, log.read_text()[-2000:]
        finally:
            _stop(launched)
