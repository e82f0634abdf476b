"""The cell file's ``discovery:`` block (core/discovery.py): what it accepts, what it refuses with
the key and the reason, and the environment it gives a node and a tool."""

from __future__ import annotations

from typing import Any

import pytest

from packml_ros2.core import ConfigError, parse_cell
from packml_ros2.core.discovery import DiscoveryConfig, environment, from_document


def cell(discovery: Any) -> dict[str, Any]:
    return {"cell": "c", "units": {"u": {"persistence": False}}, "discovery": discovery}


def test_a_server_a_domain_and_the_server_hosted() -> None:
    d = parse_cell(cell({"domain": 17, "server": "127.0.0.1:11811", "host_server": True})).discovery
    assert d == DiscoveryConfig(17, (("127.0.0.1", 11811),), True)
    assert environment(d) == {"ROS_DOMAIN_ID": "17", "ROS_DISCOVERY_SERVER": "127.0.0.1:11811"}
    assert environment(d, super_client=True)["ROS_SUPER_CLIENT"] == "TRUE"


def test_defaults_and_several_servers() -> None:
    assert parse_cell(cell(None)).discovery == DiscoveryConfig()
    assert environment(DiscoveryConfig()) == {}
    d = parse_cell(cell({"server": ["robot-pc", "[::1]:11812"]})).discovery
    assert d.servers == (("robot-pc", 11811), ("::1", 11812))
    assert d.server_text == "robot-pc:11811;[::1]:11812"


@pytest.mark.parametrize(
    ("block", "key", "words"),
    [
        ({"domain": 150}, "discovery.domain", "not a safe ROS_DOMAIN_ID"),
        ({"domain": "7"}, "discovery.domain", "expected an integer"),
        ({"server": "a b:1"}, "discovery.server", "not an address or host name"),
        ({"server": "-a"}, "discovery.server", "not an address or host name"),
        ({"server": "h:70000"}, "discovery.server", "port must be 1..65535"),
        ({"server": 11811}, "discovery.server", "expected host:port"),
        ({"server": [f"h{i}" for i in range(9)]}, "discovery.server", "at most 8"),
        ({"host_server": True}, "discovery.host_server", "needs a server address"),
        ({"host_server": "yes", "server": "h"}, "discovery.host_server", "true or false"),
        ({"serverr": "h"}, "discovery.serverr", "did you mean 'server'"),
        ([1], "discovery", "expected a mapping"),
    ],
)
def test_refused_with_the_key_and_the_reason(block: Any, key: str, words: str) -> None:
    with pytest.raises(ConfigError) as refused:
        parse_cell(cell(block))
    assert any(path == key and words in why for path, why in refused.value.problems), refused.value.problems  # fmt: skip


def test_a_node_started_by_hand_reads_only_a_valid_block() -> None:
    assert from_document(cell({"server": "h:1"})).servers == (("h", 1),)  # type: ignore[union-attr]
    assert from_document(cell({"server": "h:0"})) is None
    assert from_document({"cell": "c"}) is None and from_document([1]) is None
