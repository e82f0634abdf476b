"""The SROS2 permission policy of a cell, generated from its cell file (``packml policy``).

DDS traffic on a ROS domain is not authenticated: whoever joins the domain may call a unit's
services with any ``source``. With a ROS 2 installation whose middleware has DDS Security (the
pinned Fast DDS wheels this project runs on have not), SROS2 closes that: each process gets an
enclave (a key and signed permissions), and the permissions come from a policy file
(``ros2 security create_permission <keystore> <enclave> <policy.xml>``, or
``ros2 security generate_artifacts -k <keystore> -p <policy.xml>``).

The policy written here names exactly what the cell's nodes serve, publish and subscribe. The
nodes are built from the cell file on a private ROS context with discovery off (no persistence
is opened, nothing is sent) and asked for their endpoints, so no name is written twice. Enclaves:

- ``/<cell>/<unit>``: a unit (or its PLC bridge): replies to its services, publishes its topics;
- ``/<cell>/<unit>/<em>``: an EM: publishes the unit's ``em_reports`` and ``em_heartbeats``, reads
  its ``status``; an EM that runs as a program of its own or is started elsewhere (not built
  here) gets what the unit's interface gives an EM (:mod:`.ros.interface`: its inputs and
  ``EM_FOLLOWS``) — anything else its program uses is added to its enclave by hand;
- ``/<cell>/coordinator``: its own services and topics; reads the units, calls their services;
- ``/<cell>/hmi``, ``/<cell>/opcua``, ``/<cell>/operator`` (the ``packml`` verbs, ``ros2``,
  recorders): read every topic of the cell and call every service of it.

No other enclave may call a unit: an EM cannot command it, a face cannot publish an EM report.
"""

from __future__ import annotations

import dataclasses
import os
import random
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

from .launcher import Plan, build_nodes
from .ros import interface

#: Topics every ROS node uses (logging, parameter events).
COMMON_PUBLISH = ("/rosout", "/parameter_events")
COMMON_SUBSCRIBE = ("/parameter_events",)
#: The processes that operate a cell from outside (each an enclave of its own).
FACES = ("hmi", "opcua", "operator")
VERSION = "0.2.0"  #: the sros2 policy format


@dataclass
class Endpoints:
    """What one node (one enclave) may do: fully qualified names."""

    enclave: str
    ns: str
    node: str
    publish: set[str] = field(default_factory=set)
    subscribe: set[str] = field(default_factory=set)
    reply: set[str] = field(default_factory=set)
    request: set[str] = field(default_factory=set)


def _of(node: Any, enclave: str) -> Endpoints:
    """The endpoints ``node`` has created (read from its own graph: no discovery needed)."""
    name, ns = node.get_name(), node.get_namespace()

    def names(pairs: Iterable[tuple[str, Any]]) -> set[str]:
        return {n for n, _ in pairs}

    return Endpoints(
        enclave,
        ns,
        name,
        publish=names(node.get_publisher_names_and_types_by_node(name, ns)) | set(COMMON_PUBLISH),
        subscribe=names(node.get_subscriber_names_and_types_by_node(name, ns))
        | set(COMMON_SUBSCRIBE),
        reply=names(node.get_service_names_and_types_by_node(name, ns)),
    )


def _em(unit: str, em: str) -> Endpoints:
    """The enclave of EM ``em`` of the unit ``unit`` (``/cell/unit``) from the unit's interface:
    for an EM that is not built here (a program of its own, or started elsewhere)."""
    inputs = interface.topics(interface.Role.INPUT)
    follows = [interface.TOPIC[name] for name in interface.EM_FOLLOWS]
    return Endpoints(
        f"{unit}/{em}",
        unit,
        em,
        publish={t.path(unit) for t in inputs} | set(COMMON_PUBLISH),
        subscribe={t.path(unit) for t in follows} | set(COMMON_SUBSCRIBE),
    )


def _without_plc(plan: Plan) -> Plan:
    """``plan`` with no persistence (a running cell holds its stores: the units' and the line's)
    and a PLC unit's bridge built as a unit node: it serves and publishes the same names (and
    would connect to its PLC)."""
    units = {
        n: dataclasses.replace(u, plc=None, persistence_path=None)
        for n, u in plan.cell.units.items()
    }
    line = dataclasses.replace(plan.cell.line, store=None)
    return dataclasses.replace(plan, cell=dataclasses.replace(plan.cell, units=units, line=line))


@contextmanager
def _private_context() -> Iterator[Any]:
    """A ROS context that discovers nothing and sends nothing off this process."""
    import rclpy
    from rclpy.context import Context

    saved = os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE")
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "OFF"
    context = Context()
    try:
        args = ["--ros-args", "--log-level", "warn", "--disable-rosout-logs"]  # no "unit up" lines
        rclpy.init(args=args, context=context, domain_id=random.randint(150, 230))
        yield context
    finally:
        if context.ok():
            context.try_shutdown()
        if saved is None:
            os.environ.pop("ROS_AUTOMATIC_DISCOVERY_RANGE", None)
        else:
            os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = saved


def endpoints(plan: Plan) -> list[Endpoints]:
    """Every enclave of the cell of ``plan`` (:func:`packml_ros2.launcher.plan`) with what it
    may do, in a stable order."""
    cell = plan.cell
    base = f"/{cell.cell}"
    with _private_context() as context:
        nodes = build_nodes(_without_plc(plan), context=context)
        try:
            out = [_of(node, node.get_fully_qualified_name()) for node in nodes]
        finally:
            for node in nodes:
                getattr(node, "close", node.destroy_node)()
    built = {e.enclave for e in out}
    out += [
        _em(f"{base}/{r.unit}", r.em) for r in plan.ems if f"{base}/{r.unit}/{r.em}" not in built
    ]
    units = [e for e in out if e.ns == base and e.node in cell.units]
    cell_topics = set().union(*(e.publish for e in out)) - set(COMMON_PUBLISH) - {"/diagnostics"}
    cell_services = set().union(*(e.reply for e in out))
    for e in out:
        if e.node == "coordinator" and e.ns == base:
            e.request = set().union(*(u.reply for u in units))
    for face in FACES:
        out.append(
            Endpoints(
                f"{base}/{face}",
                base,
                face,
                publish=set(COMMON_PUBLISH),
                subscribe=cell_topics | {"/diagnostics", *COMMON_SUBSCRIBE},
                request=cell_services,
            )
        )
    return out


def policy_xml(enclaves: Iterable[Endpoints]) -> str:
    """The sros2 policy document (format 0.2.0) of ``enclaves``."""
    root = ET.Element("policy", version=VERSION)
    parent = ET.SubElement(root, "enclaves")
    for e in enclaves:
        enclave = ET.SubElement(parent, "enclave", path=e.enclave)
        profile = ET.SubElement(ET.SubElement(enclave, "profiles"), "profile", ns=e.ns, node=e.node)
        for tag, item, rule, names in (
            ("topics", "topic", "publish", e.publish),
            ("topics", "topic", "subscribe", e.subscribe),
            ("services", "service", "reply", e.reply),
            ("services", "service", "request", e.request),
        ):
            if names:
                group = ET.SubElement(profile, tag, {rule: "ALLOW"})
                for name in sorted(names):
                    ET.SubElement(group, item).text = name
    ET.indent(root)
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"
