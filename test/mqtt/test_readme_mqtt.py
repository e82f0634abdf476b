"""The README's MQTT commands, verbatim, on a host of their own (a network namespace: its
127.0.0.1:1883 is the README's broker, whatever runs on this machine's)."""

from __future__ import annotations

import shlex
from collections.abc import Iterator
from pathlib import Path

import pytest

from packml_ros2.testing.netns import Network, ip, why_no_namespaces
from test.workspace.tools import ROOT, Background, code_blocks, console_commands, shell, shown_in

pytestmark = [
    pytest.mark.ros,
    pytest.mark.skipif(bool(why_no_namespaces()), reason=why_no_namespaces()),
]


def mqtt_blocks() -> list[list[tuple[str, list[str]]]]:
    blocks = [console_commands(b) for b in code_blocks("console")]
    start = next(i for i, b in enumerate(blocks) if any("--mqtt" in c for c, _ in b))
    return blocks[start : start + 2]


@pytest.fixture
def host() -> Iterator[Network]:
    net = Network(["plant"], subnet="10.231.0", prefix="mq")
    try:
        net.setup()
        yield net
    finally:
        for pid in ip("netns", "pids", net.ns["plant"], check=False).stdout.split():
            ip("netns", "exec", net.ns["plant"], "kill", pid, check=False)  # the README's broker
        net.teardown()


def test_the_readme_mqtt_commands(host: Network, tmp_path: Path) -> None:
    (broker, _), (launch, launched) = mqtt_blocks()[0]
    [(subscribe, received)] = mqtt_blocks()[1]
    assert broker == "/usr/sbin/mosquitto -d" and launch.endswith("--mqtt"), (broker, launch)
    inside = " ".join(host.exec_args("plant"))
    started = shell(f"{inside} {broker}", tmp_path, ROOT, timeout=30)
    assert started.returncode == 0, started.stdout
    cell = Background(f"exec {inside} {launch}", tmp_path, ROOT, tmp_path / "launch.log")
    try:
        cell.wait_for("MQTT Sparkplug B edge node", 120)
        assert shown_in(launched, cell.output()) is None, (launched, cell.output())
        got = shell(f"{inside} bash -c {shlex.quote(subscribe + ' -W 30')}", tmp_path, ROOT, 60)
        assert got.returncode == 0 and shown_in(received, got.stdout) is None, got.stdout
        assert cell.ctrl_c(60) == 0, cell.output()[-3000:]
    finally:
        if cell.proc.poll() is None:
            cell.kill()
