"""The README's MQTT commands, verbatim, on a host of their own (a network namespace: its
127.0.0.1:1883 is the README's broker, whatever runs on this machine's)."""

from __future__ import annotations

import shlex
from collections.abc import Iterator
from pathlib import Path

import pytest

from packml_ros2.testing.netns import Network, ip, why_no_namespaces
from test.workspace.tools import (
    README,
    ROOT,
    Background,
    code_blocks,
    console_commands,
    shell,
    shown_in,
)

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


def readme_acl() -> str:
    """The README's ACL example: the plain code block that follows "acl_file"."""
    text = README.read_text(encoding="utf-8")
    start = text.index("```\n", text.index("mosquitto's `acl_file`"))
    return text[start + 4 : text.index("```", start + 4)]


def test_the_readme_acl_lets_the_edge_node_and_scada_do_their_part_and_no_more(
    tmp_path: Path,
) -> None:
    """The demo cell behind a broker with logins and the README's ACL: the edge node (user
    packml-edge) is born and answers; SCADA (user scada) commands it and reads everything, and
    what it writes where only the edge node may write never reaches anyone."""
    import yaml

    from packml_ros2.testing.processes import Processes
    from test.mqtt.host import Broker, Host, close_all, password_file

    acl = tmp_path / "acl"
    acl.write_text(readme_acl())
    logins = password_file(tmp_path, {"packml-edge": "edge-pw-1", "scada": "scada-pw-2"})
    broker = Broker(
        tmp_path, settings=f"allow_anonymous false\npassword_file {logins}\nacl_file {acl}\n"
    )
    doc = yaml.safe_load((ROOT / "config" / "demo_cell.yaml").read_text())
    doc["defaults"]["persistence"] = {"path": str(tmp_path / "{unit}.sqlite3")}
    doc["coordinator"] = {**doc.get("coordinator", {}), "enabled": False}
    doc["mqtt"] = {
        "port": broker.port,
        "username": "packml-edge",
        "password": "env:PACKML_TEST_EDGE_PW",
    }
    cell_file = tmp_path / "demo_cell.yaml"
    cell_file.write_text(yaml.safe_dump(doc, sort_keys=False))
    procs = Processes(tmp_path)
    host = Host(broker.port, "packml", login=("scada", "scada-pw-2"))
    try:
        procs.module("unit", "packml_ros2.unit_node", str(cell_file), "robot_cell")
        procs.module("mqtt", "packml_ros2.cli.main", "mqtt", str(cell_file),
                     env={"PACKML_TEST_EDGE_PW": "edge-pw-1"})  # fmt: skip
        host.wait(lambda s: s.kind == "DBIRTH" and s.device == "robot_cell", 60, "the DBIRTH")
        # SCADA forges a DDATA: the broker drops it (scada may not write there)
        host.send(
            "spBv1.0/packml/DDATA/demo_cell/robot_cell", [("State/CurrentName", 12, "FORGED")]
        )
        mark = host.mark()
        host.send("spBv1.0/packml/DCMD/demo_cell/robot_cell",
                  [("Command/RequestId", 12, "acl-1"), ("Command/CntrlCmd", 3, 8)])  # fmt: skip
        answer = host.wait(lambda s: s.metrics.get("Command/Answer/RequestId") == "acl-1", 30,
                           "the answer to SCADA's DCMD", after=mark)  # fmt: skip
        assert answer.metrics["Command/Answer/Command"] == "Command/CntrlCmd=ABORT", answer.metrics
        assert not [s for s in host.since(0) if s.metrics.get("State/CurrentName") == "FORGED"]
        assert host.errors == []
    finally:
        failures = close_all(host, procs, broker)
    assert not failures, failures
