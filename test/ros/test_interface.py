"""Issue 28 item 3: a unit's ROS interface is declared once (``packml_ros2.ros.interface``), and
what users meet agrees with it: a running unit node and a PLC bridge serve exactly its services
with their types and publish and subscribe exactly its topics with their QoS (read from the ROS
graph over DDS), the proxies call and follow it, the recorder records it, and the README's lists
name every service and topic of it (the README once lacked ``set_remote_commands``)."""

from __future__ import annotations

import re
import socket
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from packml_interfaces.msg import Result
from packml_interfaces.srv import AckAlarms, Command
from rclpy.qos import DurabilityPolicy, ReliabilityPolicy

from packml_ros2 import client
from packml_ros2.bag import topics as bag_topics
from packml_ros2.ros import interface
from packml_ros2.testing.processes import Processes
from test.ros.cells import start_unit_process, write_cell

ROOT = Path(__file__).resolve().parents[2]
#: rclpy's parameter services, which every node serves
PARAMETER_SERVICES = {"describe_parameters", "get_parameter_types", "get_parameters",
                      "get_type_description", "list_parameters", "set_parameters",
                      "set_parameters_atomically"}  # fmt: skip
#: topics every node publishes or subscribes besides its own
COMMON = {"/rosout", "/parameter_events"}


def _names_section() -> str:
    """The README's paragraph that names a unit's services and topics."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    section = text.split("### Names", 1)[1]
    return " ".join(section.split("Every refusal", 1)[0].split())


def _listed(text: str) -> set[str]:
    """The names in backticks (``<unit>/`` dropped), not types or field declarations."""
    names = (re.sub(r"^<unit>/", "", n) for n in re.findall(r"`([^`]+)`", text))
    return {n for n in names if re.fullmatch(r"/?[a-z_]+", n)}


def test_the_readme_names_every_service_and_topic_the_interface_declares() -> None:
    names = _names_section()
    serves, publishes = names.split("A unit serves", 1)[1].split("; it publishes", 1)
    shortcuts = interface.SHORTCUTS
    span = f"`<unit>/{shortcuts[0].name}` ... `<unit>/{shortcuts[-1].name}`"
    assert span in serves, "the README spells the Trigger shortcuts as a range"
    others = {s.name for s in interface.SERVICES if s.command is None}
    listed = _listed(serves) - {shortcuts[0].name, shortcuts[-1].name}
    assert listed == others, (
        f"README lacks {sorted(others - listed)}, names undeclared {sorted(listed - others)}"
    )
    topics = {t.name for t in interface.TOPICS}
    assert _listed(publishes) == topics, (
        f"README lacks {sorted(topics - _listed(publishes))}, "
        f"names undeclared {sorted(_listed(publishes) - topics)}"
    )


def test_the_proxies_and_the_recorder_read_the_declaration() -> None:
    assert {s.name: s.type for s in interface.SERVICES} == client.SERVICES
    assert set(client.UnitProxy.topics) <= {t.name for t in interface.topics(interface.Role.OUTPUT)}
    recorded = [t for t in interface.TOPICS if t.recorded]
    assert {t.name: t.type_name for t in recorded} == bag_topics.UNIT_TOPICS
    for t in recorded:
        assert bag_topics.PUBLISHER_QOS[t.name] == t.qos
    outputs = {t.name for t in interface.topics(interface.Role.OUTPUT)}
    assert set(bag_topics.OUTPUT_TOPICS) == outputs
    derived = {t.name for t in interface.topics(interface.Role.DERIVED)}
    assert set(bag_topics.DERIVED_TOPICS) == derived
    assert set(bag_topics.INPUT_TOPICS) == {t.name for t in recorded} - outputs - derived
    assert {t.name for t in interface.TOPICS if t.latched} >= set(bag_topics.LATCHED_OUTPUTS)
    for t in interface.TOPICS:  # the type names rosbag2 and `ros2 topic` spell
        assert bag_topics.msg_class(t.type_name) is t.type


def _graph(node: Any, name: str, ns: str) -> tuple[set[tuple[str, str]], ...]:
    """(services, publishers, subscriptions) of node ``ns/name`` as (name, type) pairs, names
    relative to the node (``/diagnostics`` and the common topics as they are)."""
    prefix = f"{ns}/{name}/"

    def rel(pairs: Any) -> set[tuple[str, str]]:
        return {(n[len(prefix) :] if n.startswith(prefix) else n, types[0]) for n, types in pairs}

    return (
        rel(node.get_service_names_and_types_by_node(name, ns)),
        rel(node.get_publisher_names_and_types_by_node(name, ns)),
        rel(node.get_subscriber_names_and_types_by_node(name, ns)),
    )  # fmt: skip


def _wait_graph(node: Any, name: str, ns: str, expected: tuple[set[tuple[str, str]], ...],
                timeout: float = 30.0) -> tuple[set[tuple[str, str]], ...]:  # fmt: skip
    """The node's graph once it equals ``expected`` (discovery), or as it is at the timeout."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            seen = _graph(node, name, ns)
        except Exception:  # the node is not discovered yet
            seen = (set(), set(), set())
        seen = ({s for s in seen[0] if s[0] not in PARAMETER_SERVICES}, seen[1], seen[2])
        if seen == expected or time.monotonic() > deadline:
            return seen
        time.sleep(0.05)


def _declared(*topics: interface.Topic) -> tuple[set[tuple[str, str]], ...]:
    services = {(s.name, s.type_name) for s in interface.SERVICES}
    published = {(t.name, t.type_name) for t in topics if t.published}
    published |= {("/rosout", "rcl_interfaces/msg/Log"),
                  ("/parameter_events", "rcl_interfaces/msg/ParameterEvent")}  # fmt: skip
    subscribed = {(t.name, t.type_name) for t in topics if not t.published}
    return services, published, subscribed


def _offered(node: Any, topic: str) -> Any:
    (info,) = node.get_publishers_info_by_topic(topic)
    return info.qos_profile


@pytest.mark.ros
def test_a_running_unit_serves_and_publishes_exactly_the_declared_interface(
    tmp_path: Path, ros: Any, processes: Processes
) -> None:
    path, cell = write_cell(tmp_path, {"filler": {"equipment_modules": {"robot": {}}}})
    start_unit_process(processes, path, "filler")
    ros.wait_for_service(Command, f"/{cell}/filler/command", 30)
    expected = _declared(*interface.TOPICS)
    seen = _wait_graph(ros.node, "filler", f"/{cell}", expected)
    assert seen == expected, "\n".join(
        f"{what}: missing {sorted(e - s)}, undeclared {sorted(s - e)}"
        for what, e, s in zip(
            ("services", "publishers", "subscriptions"), expected, seen, strict=True
        )
        if e != s
    )
    for t in interface.topics():  # the QoS every follower subscribes with
        if not t.published or t.name == "/diagnostics":
            continue
        offered = _offered(ros.node, t.path(f"/{cell}/filler"))
        assert offered.durability == t.qos.durability, t.name
        assert offered.reliability == t.qos.reliability == ReliabilityPolicy.RELIABLE, t.name
        assert t.latched == (offered.durability == DurabilityPolicy.TRANSIENT_LOCAL), t.name
        if t.leased:  # presence: the status writer's liveliness lease is the cell's unit_lease
            assert offered.liveliness_lease_duration.nanoseconds == 3 * 10**9, t.name


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.ros
def test_a_plc_bridge_serves_the_declared_services_and_refuses_what_opc_30050_lacks(
    tmp_path: Path, ros: Any, processes: Processes
) -> None:
    """With its PLC not there, the bridge serves every declared service, publishes ``config``
    and ``/diagnostics`` and none of the unit's outputs (a PLC that is gone looks gone); a
    service OPC 30050 has no method for is refused with the declared phrase."""
    endpoint = f"opc.tcp://127.0.0.1:{_free_port()}"  # nothing listens there
    path, cell = write_cell(tmp_path, {"wrapper": {"plc": {"endpoint": endpoint}}})
    processes.module("plc_wrapper", "packml_ros2.plc.node", str(path), "wrapper")
    ros.wait_for_service(AckAlarms, f"/{cell}/wrapper/ack_alarms", 30)
    kept = [t for t in interface.TOPICS if t.plc and t.role is not interface.Role.OUTPUT]
    assert {t.name for t in kept} == {"config", "/diagnostics"}
    expected = _declared(*kept)
    seen = _wait_graph(ros.node, "wrapper", f"/{cell}", expected)
    assert seen == expected
    assert interface.SERVICE["ack_alarms"].plc_lacks
    resp = ros.call(AckAlarms, f"/{cell}/wrapper/ack_alarms", AckAlarms.Request(all=True))
    assert not resp.accepted and resp.result == Result.NOT_SUPPORTED
    assert interface.SERVICE["ack_alarms"].plc_lacks in resp.message


@pytest.mark.ros
def test_a_node_that_lacks_a_handler_for_a_declared_service_does_not_start(ros: Any) -> None:
    """A service added to the declaration and forgotten in a node fails at its start, named."""
    from rclpy.node import Node

    node = Node("lacking", namespace="/interface_test", context=ros.context)
    try:
        handlers = {s.name: (lambda req, resp: resp) for s in interface.SERVICES}
        del handlers["set_interlock"]
        with pytest.raises(ValueError, match="lacking has no handler for service set_interlock"):
            interface.create_services(node, handlers, lambda cmd, req, resp: resp)
    finally:
        node.destroy_node()


def test_the_policy_gives_an_em_that_is_not_built_here_what_the_interface_gives_an_em(
    tmp_path: Path,
) -> None:
    """``packml policy``: an EM run elsewhere (``external``) gets an enclave from the unit's
    interface, the same as an EM whose node the generator built and asked (before: none, so
    under SROS2 its reports were denied)."""
    from packml_ros2 import launcher, policy

    ems = {"local": {"sim": {}}, "elsewhere": {"external": True}}
    path, cell = write_cell(tmp_path, {"filler": {"equipment_modules": ems, "persistence": None}})
    enclaves = {e.enclave: e for e in policy.endpoints(launcher.plan(path))}
    base = f"/{cell}/filler"
    built, declared = enclaves[f"{base}/local"], enclaves.get(f"{base}/elsewhere")
    assert declared is not None, sorted(enclaves)
    assert (declared.ns, declared.node) == (base, "elsewhere")
    assert (
        declared.publish
        == built.publish
        == {f"{base}/em_reports", f"{base}/em_heartbeats", "/rosout", "/parameter_events"}
    )
    assert declared.subscribe == built.subscribe
    assert not declared.reply and not declared.request


def test_unit_node_help_lists_every_declared_service_and_topic() -> None:
    """``unit_node --help`` (the README points to it) prints the declaration."""
    import shutil
    import subprocess

    exe = shutil.which("unit_node") or str(Path(sys.executable).with_name("unit_node"))
    out = subprocess.run([exe, "--help"], capture_output=True, text=True, timeout=60, check=True)
    listed = {line.split()[0] for line in out.stdout.splitlines() if line.startswith("  ")}
    assert listed == {s.name for s in interface.SERVICES} | {t.name for t in interface.TOPICS}
    for s in interface.SERVICES:
        assert f"{s.type_name} " in out.stdout, s.name


def test_every_hmi_unit_action_is_a_declared_service_with_a_level() -> None:
    """The HMI bridge calls a unit's services by the action's name (through the proxies)."""
    from packml_ros2.hmi import access, bridge

    assert set(bridge.UNIT_ACTIONS) <= set(interface.SERVICE)
    assert set(bridge.UNIT_ACTIONS) == set(access.UNIT_ACTION_LEVEL)
