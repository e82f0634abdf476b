"""How a cell's processes find each other (the cell file's ``discovery:`` block, issue 29).

    discovery:
      domain: 17                  # ROS_DOMAIN_ID of every process of the cell (0..101, 215..232)
      server: 127.0.0.1:11811     # a Fast DDS Discovery Server (host:port; several: a list)
      host_server: true           # `packml launch` runs that server itself (its address on this host)

Without ``server`` the cell uses DDS simple discovery (multicast, or the loopback profile when the
discovery range is LOCALHOST). With it, every process of the cell is a Discovery Server *client*
(``ROS_DISCOVERY_SERVER``); the tools that look at the whole graph (``packml status``, ``watch``,
``cmd``, the HMI, the OPC UA face, the recorder) are *super clients* (``ROS_SUPER_CLIENT``), as the
``ros2`` CLI must be. The environment is what Fast DDS and rcl read, so a process started by hand
with the same variables joins the same cell. Pure: the ROS shell applies :func:`environment`.
"""

from __future__ import annotations

import ipaddress
import re
from collections.abc import Mapping
from dataclasses import dataclass

from . import schema as sc
from .schema import Node, invalid

#: ROS_DOMAIN_IDs that are safe on Linux (ROS 2 "The ROS_DOMAIN_ID" concept page).
DOMAINS = (range(102), range(215, 233))
DEFAULT_PORT = 11811
MAX_SERVERS = 8
KEYS = ("domain", "server", "host_server")
_LABEL = re.compile(r"[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?")


@dataclass(frozen=True)
class DiscoveryConfig:
    domain: int | None = None  #: None: the environment's ROS_DOMAIN_ID (default 0)
    servers: tuple[tuple[str, int], ...] = ()  #: (host, port) of each Discovery Server
    host_server: bool = False  #: ``packml launch`` runs the (first) server

    @property
    def server_text(self) -> str:
        """``ROS_DISCOVERY_SERVER``'s value: the servers separated by ``;``."""
        return ";".join(f"[{h}]:{p}" if ":" in h else f"{h}:{p}" for h, p in self.servers)


def _server(n: Node) -> tuple[str, int]:
    if not isinstance(n.value, str) or not n.value or len(n.value) > 255:
        raise invalid(
            f"expected host:port (e.g. 127.0.0.1:{DEFAULT_PORT}), got {sc.shown(n.value)}"
        )
    host, sep, port_text = n.value.strip().rpartition(":")
    if not sep:
        host, port_text = port_text, str(DEFAULT_PORT)
    host = host.strip("[]")
    try:
        ipaddress.ip_address(host)
    except ValueError:
        if not all(_LABEL.fullmatch(part) for part in host.split(".")):
            raise invalid(
                f"{sc.shown(n.value)}: {sc.shown(host)} is not an address or host name"
            ) from None
    if not port_text.isdigit() or not 1 <= int(port_text) <= 65535:
        raise invalid(f"{sc.shown(n.value)}: the port must be 1..65535")
    return host, int(port_text)


def _domain(n: Node) -> int:
    value = sc.integer(0, 232)(n)
    if not any(value in r for r in DOMAINS):
        raise invalid(f"{value} is not a safe ROS_DOMAIN_ID on Linux (0..101 or 215..232)")
    return value


def parse_discovery(n: Node) -> DiscoveryConfig:
    """The ``discovery:`` block (problems are added to ``n``'s list)."""
    n.check_keys(set(KEYS))
    domain = n.get("domain", _domain, None)
    m = n.mapping()
    raw = m.get("server")
    nodes = (
        n.list_at("server")
        if isinstance(raw, list)
        else ([n.child("server", raw)] if "server" in m else [])
    )
    if len(nodes) > MAX_SERVERS:
        n.child("server", raw).error(f"at most {MAX_SERVERS} servers")
        nodes = nodes[:MAX_SERVERS]
    servers = tuple(s for s in (x.parse(_server, None) for x in nodes) if s is not None)
    host = n.get("host_server", sc.boolean, False)
    if host and not servers:
        n.child("host_server", host).error("host_server needs a server address to listen on")
    return DiscoveryConfig(domain, servers, host)


def environment(d: DiscoveryConfig, super_client: bool = False) -> dict[str, str]:
    """The variables that put a process into the cell's discovery setup."""
    env: dict[str, str] = {}
    if d.domain is not None:
        env["ROS_DOMAIN_ID"] = str(d.domain)
    if d.servers:
        env["ROS_DISCOVERY_SERVER"] = d.server_text
        if super_client:
            env["ROS_SUPER_CLIENT"] = "TRUE"
    return env


def from_document(doc: object) -> DiscoveryConfig | None:
    """The ``discovery:`` block of a parsed cell document, None when absent or invalid (the
    cell's full validation reports it)."""
    if not isinstance(doc, Mapping) or not isinstance(doc.get("discovery"), Mapping):
        return None
    n = Node(doc["discovery"], "discovery")
    d = parse_discovery(n)
    return None if n.problems else d
