"""Issue 15, item 1: no secret on any topic, in any log or in a recorded bag. A cell with an HMI
token (from a file) and an OPC UA password (from the environment) runs with its HMI and OPC UA
server (`packml launch --hmi --opcua`) while `packml record` records it; wrong and right tokens
and passwords are tried. Then every topic's raw bytes, every process's output, the ROS log
directory and the bag are searched for both secrets."""

from __future__ import annotations

import asyncio
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import pytest
import yaml
from rclpy.qos import QoSProfile

from packml_ros2.bag.topics import msg_class
from test.ros.cells import write_cell

pytestmark = pytest.mark.ros

TOKEN = "hmi-T0ken-secret-4711"
PASSWORD = "opcua-Passw0rd-secret-0815"
FAST = {"resetting": 0.1, "starting": 0.1, "stopping": 0.1, "clearing": 0.1, "aborting": 0.05}
PACKML = [sys.executable, "-m", "packml_ros2.cli.main"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _bag_bytes(bag: Path) -> bytes:
    """The bag's files and every message as a reader gets it (mcap chunks are compressed)."""
    from rosbags.highlevel import AnyReader

    files = b"".join(f.read_bytes() for f in bag.rglob("*") if f.is_file())
    with AnyReader([bag]) as reader:
        return files + b"".join(bytes(raw) for _, _, raw in reader.messages())


def _wait(predicate: Any, timeout: float, what: str, log: Path | None = None) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        found = predicate()
        if found:
            return found
        time.sleep(0.05)
    raise AssertionError(
        f"{what} not within {timeout} s" + (f":\n{log.read_text()}" if log else "")
    )


class Topics:
    """Every topic of the cell (and /rosout), subscribed raw with its publisher's QoS."""

    def __init__(self, node: Any, prefix: str) -> None:
        self.node, self.prefix = node, prefix
        self.data: dict[str, list[bytes]] = {}
        self._lock = threading.Lock()

    def follow(self) -> None:
        for name, types in self.node.get_topic_names_and_types():
            if name in self.data or not (name.startswith(self.prefix) or name == "/rosout"):
                continue
            publishers = self.node.get_publishers_info_by_topic(name)
            if not publishers:
                continue
            qos: QoSProfile = publishers[0].qos_profile
            self.data[name] = []
            self.node.create_subscription(
                msg_class(types[0]), name, lambda m, n=name: self._got(n, m),
                QoSProfile(depth=100, reliability=qos.reliability, durability=qos.durability),
                raw=True,
            )  # fmt: skip

    def _got(self, name: str, raw: bytes) -> None:
        with self._lock:
            self.data[name].append(bytes(raw))

    def received(self, suffix: str) -> list[bytes]:
        with self._lock:
            return [m for name, ms in self.data.items() if name.endswith(suffix) for m in ms]


async def _opcua_login(url: str, password: str) -> bool:
    from asyncua import Client

    client = Client(url, timeout=10)
    client.set_user("operator")
    client.set_password(password)
    try:
        await client.connect()
    except Exception:
        return False
    await client.disconnect()
    return True


def test_no_secret_on_topics_in_logs_or_in_a_bag(ros: Any, tmp_path: Path) -> None:
    path, cell = write_cell(
        tmp_path,
        {
            "filler": {
                "equipment_modules": {"nozzle": {"sim": {"durations": FAST, "cycle_time": 0.2}}}
            }
        },
    )
    (tmp_path / "hmi.token").write_text(TOKEN + "\n")
    opcua_port = _free_port()
    doc = yaml.safe_load(path.read_text())
    doc["hmi"] = {"host": "127.0.0.1", "port": 0, "token": "file:hmi.token"}
    doc["opcua"] = {"port": opcua_port, "state_dir": str(tmp_path / "opcua"),
                    "security_policies": ["None"], "users": {"operator": "env:PACKML_LEAK_PW"}}  # fmt: skip
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    log_dir = tmp_path / "ros_log"
    env = dict(os.environ, PYTHONUNBUFFERED="1", PACKML_LEAK_PW=PASSWORD, ROS_LOG_DIR=str(log_dir))
    launch_log, record_log, bag = tmp_path / "launch.log", tmp_path / "record.log", tmp_path / "bag"
    topics = Topics(ros.node, f"/{cell}/")
    with launch_log.open("wb") as out:
        launch = subprocess.Popen([*PACKML, "launch", str(path), "--hmi", "--opcua"],
                                  stdout=out, stderr=subprocess.STDOUT, env=env)  # fmt: skip
    record: subprocess.Popen[bytes] | None = None
    try:
        _wait(lambda: "is up" in launch_log.read_text() and "OPC UA server" in launch_log.read_text(),
              90, "the cell, its HMI and its OPC UA server", launch_log)  # fmt: skip
        url = _wait(lambda: re.search(r"(http://127\.0\.0\.1:\d+/)", launch_log.read_text()),
                    30, "the HMI's address", launch_log).group(1)  # fmt: skip
        with record_log.open("wb") as out:
            record = subprocess.Popen([*PACKML, "record", cell, "-o", str(bag)], stdout=out,
                                      stderr=subprocess.STDOUT, env=env)  # fmt: skip
        _wait(lambda: f"receiving /{cell}/filler" in record_log.read_text(), 30, "the recorder",
              record_log)  # fmt: skip

        def followed() -> bool:
            topics.follow()
            return bool(topics.received("filler/config") and topics.received("filler/admin"))

        _wait(followed, 30, "the unit's latched configuration and its admin data")

        # wrong and right secrets, on both faces
        for guess in ("guess-1", TOKEN[:-1], TOKEN + "x"):
            r = httpx.post(f"{url}api/units/filler/command", json={"command": "reset"},
                           headers={"Authorization": f"Bearer {guess}"}, timeout=10)  # fmt: skip
            assert r.status_code == 403 and guess not in r.text
        r = httpx.post(f"{url}api/units/filler/command", json={"command": "reset"},
                       headers={"Authorization": f"Bearer {TOKEN}"}, timeout=10)  # fmt: skip
        assert r.status_code == 200 and r.json()["accepted"], r.text
        opcua = f"opc.tcp://127.0.0.1:{opcua_port}/"
        assert not asyncio.run(_opcua_login(opcua, PASSWORD[:-1]))
        assert asyncio.run(_opcua_login(opcua, PASSWORD))

        _wait(lambda: any(b"RESETTING" in m for m in topics.received("filler/transitions")), 30,
              "the reset on the transitions topic")  # fmt: skip
        record.send_signal(signal.SIGINT)
        assert record.wait(30) == 0, record_log.read_text()
    finally:
        if record is not None and record.poll() is None:
            record.kill()
        launch.send_signal(signal.SIGINT)
        try:
            launch.wait(30)
        except subprocess.TimeoutExpired:
            launch.kill()

    # the searches can find: the config on the topic and in the bag is there, redacted
    (config,) = topics.received("filler/config")
    assert b"<redacted>" in config and b"file:hmi.token" not in config
    bag_bytes = _bag_bytes(bag)
    assert b"<redacted>" in bag_bytes and b"env:PACKML_LEAK_PW" not in bag_bytes
    logs = b"".join(f.read_bytes() for f in log_dir.rglob("*") if f.is_file())
    assert b"wrong access token" in launch_log.read_bytes() + logs  # the guesses were logged...
    places = {
        "topics": b"".join(m for ms in topics.data.values() for m in ms),
        "bag": bag_bytes,
        "launch output": launch_log.read_bytes(),
        "record output": record_log.read_bytes(),
        "ROS logs": logs,
        "unit store": b"".join(f.read_bytes() for f in tmp_path.glob("*.sqlite3*")),
    }
    for secret in (TOKEN, PASSWORD, "guess-1"):  # ...but never a token or a guess
        for where, data in places.items():
            assert secret.encode() not in data, f"{secret!r} in {where}"
    assert len(topics.data) >= 8, sorted(topics.data)
