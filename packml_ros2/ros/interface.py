"""A PackML unit's ROS interface, declared once: its services and topics, their types, QoS and
latching.

Every program that serves, publishes, calls, follows or records a unit reads this declaration
instead of spelling the names again: the unit node (:mod:`packml_ros2.unit_node`) and the PLC
bridge (:mod:`packml_ros2.plc.node`) create their endpoints from it, the proxies of the CLI, the
coordinator, the HMI and the OPC UA server (:mod:`packml_ros2.client`) call and follow it, the
recorder (:mod:`packml_ros2.bag.topics`) records it, EMs (:mod:`packml_ros2.equipment_module`,
the simulator) report to it and follow it, the launcher waits on it, and a test checks the
README's lists against it. The policy generator (:mod:`packml_ros2.policy`) reads the endpoints
the nodes created from it, and gives an EM it did not build what this declaration gives an EM.

Names are relative to the unit's node (``status`` is ``/<cell>/<unit>/status``) unless they start
with ``/`` (``/diagnostics``).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from enum import Enum
from functools import partial
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from packml_interfaces.msg import (
    Admin,
    AlarmList,
    EmReport,
    RecipeOrder,
    StackLight,
    Status,
    TransitionEvent,
    UnitInput,
    UnitSnapshot,
)
from packml_interfaces.srv import (
    AckAlarms,
    Command,
    QueryAlarms,
    ResetAlarms,
    ResetCounters,
    ResetTimes,
    SetAlarm,
    SetEmActive,
    SetInterlock,
    SetMachSpeed,
    SetMode,
    SetProduct,
    SetRecipe,
    SetRemoteCommands,
    SetUnitParameters,
)
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile
from std_msgs.msg import String
from std_srvs.srv import Trigger

from .. import qos, responses
from ..core.numbers import Cmd
from ..responses import TRIGGER_SHORTCUTS


class Role(Enum):
    """What a topic is to the unit."""

    OUTPUT = "output"  #: the unit publishes what its engine decided (replay compares it)
    RECORD = "record"  #: the unit publishes what a recording needs to replay it
    #: the unit publishes what follows from its outputs (a recording keeps it; replay compares
    #: the outputs it follows from: the changeover orders' recipes and answers are in the status
    #: and the input log, the stack light in the status)
    DERIVED = "derived"
    INPUT = "input"  #: the unit subscribes: its EMs publish
    DIAGNOSTIC = "diagnostic"  #: the unit publishes for the standard tools (not recorded)


@dataclass(frozen=True)
class Topic:
    """One topic of a unit."""

    name: str
    type: Any  #: the rclpy message class
    qos: QoSProfile  #: the publisher's profile (a follower subscribes with it)
    role: Role
    doc: str
    #: the PLC bridge publishes it too (while its PLC is connected)
    plc: bool = False
    #: published with DDS liveliness and the cell's ``unit_lease`` (presence, :mod:`..presence`)
    leased: bool = False
    #: ``packml record`` writes it into a bag
    recorded: bool = True

    @property
    def latched(self) -> bool:
        """A late subscriber gets the last message(s) at once (transient local durability)."""
        return bool(self.qos.durability == DurabilityPolicy.TRANSIENT_LOCAL)

    @property
    def type_name(self) -> str:
        """``pkg/msg/Name`` (as ``ros2 topic`` and rosbag2 spell it)."""
        return type_name(self.type, "msg")

    @property
    def published(self) -> bool:
        return self.role is not Role.INPUT

    def path(self, unit: str | None = None) -> str:
        """The name to create the endpoint with: ``~/name`` for the unit node itself, or the full
        name under the unit path ``unit`` (``/cell/unit``); ``/name`` as it is."""
        if self.name.startswith("/"):
            return self.name
        return f"~/{self.name}" if unit is None else f"{unit.rstrip('/')}/{self.name}"


@dataclass(frozen=True)
class Service:
    """One service of a unit."""

    name: str
    type: Any  #: the rclpy service class
    doc: str
    #: what the PLC bridge cannot do here ('' = it serves it; else it refuses with NOT_SUPPORTED
    #: and this phrase: OPC 30050 has no method for it)
    plc_lacks: str = ""
    #: the command of a Trigger shortcut (``<unit>/start``: Command START)
    command: Cmd | None = None

    @property
    def type_name(self) -> str:
        return type_name(self.type, "srv")


def type_name(cls: Any, kind: str) -> str:
    """``pkg/msg/Name`` of a generated rclpy class."""
    return f"{cls.__module__.split('.')[0]}/{kind}/{cls.__name__}"


#: The unit's topics. The order is the recorder's (a bag's connections).
TOPICS: tuple[Topic, ...] = (
    Topic("input_log", UnitInput, qos.INPUT_LOG, Role.RECORD,
          "every input the engine applied, in batches (latched: the last 5000)"),
    Topic("config", String, qos.LATCHED, Role.RECORD,
          "the cell file the unit was started with, without its secrets (latched)", plc=True),
    Topic("status", Status, qos.STATUS, Role.OUTPUT,
          "PackTags Status on every change (latched; DDS liveliness with unit_lease)",
          plc=True, leased=True),
    Topic("transitions", TransitionEvent, qos.TRANSITIONS, Role.OUTPUT,
          "every state transition (latched: the last 100)", plc=True),
    Topic("admin", Admin, qos.ADMIN, Role.OUTPUT,
          "PackTags Admin: times, counters, alarms, OEE (latched, on change and every 5 s)",
          plc=True),
    Topic("alarms", AlarmList, qos.ALARMS, Role.OUTPUT,
          "the alarm and warning lists with first-out (latched)", plc=True),
    Topic("recipe", RecipeOrder, qos.LATCHED, Role.DERIVED,
          "changeover orders to the EMs: the recipe to apply or roll back to (latched)"),
    Topic("stack_light", StackLight, qos.LATCHED, Role.DERIVED,
          "the stack light: lights and horn, on change (latched)"),
    Topic("em_reports", EmReport, qos.EM_REPORTS, Role.INPUT,
          "EM -> unit: registration, State Complete, counts, alarms, goodbyes"),
    Topic("snapshot", UnitSnapshot, qos.SNAPSHOT, Role.RECORD,
          "the engine state, when a recorder joins (latched)"),
    Topic("em_heartbeats", EmReport, qos.EM_HEARTBEATS, Role.INPUT,
          "EM -> unit heartbeats, best effort (ten per lease; their effect is in the input log)",
          recorded=False),
    Topic("/diagnostics", DiagnosticArray, qos.DIAGNOSTICS, Role.DIAGNOSTIC,
          "diagnostic_msgs: one entry for the unit, one per EM, every second", plc=True,
          recorded=False),
)  # fmt: skip

#: The PackML commands' Trigger shortcuts (``<unit>/reset`` ... ``<unit>/complete``).
SHORTCUTS: tuple[Service, ...] = tuple(
    Service(verb, Trigger, f"command {c.name} (std_srvs Trigger)", command=c)
    for verb, c in TRIGGER_SHORTCUTS
)

#: The unit's services, the Trigger shortcuts last.
SERVICES: tuple[Service, ...] = (
    Service("command", Command, "a PackML state command with its source"),
    Service("set_mode", SetMode, "a unit mode change (number or name)"),
    Service("reset_times", ResetTimes, "reset the current mode's or all times",
            "resetting times"),
    Service("reset_counters", ResetCounters, "reset the counters", "resetting counters"),
    Service("ack_alarms", AckAlarms, "acknowledge one or all alarms", "acknowledging alarms"),
    Service("reset_alarms", ResetAlarms, "clear latched alarms that are no longer active",
            "resetting alarms"),
    Service("query_alarms", QueryAlarms, "the alarm list or history, filtered and sorted"),
    Service("set_alarm", SetAlarm, "raise or clear an alarm or warning",
            "raising or clearing alarms"),
    Service("set_mach_speed", SetMachSpeed, "the machine speed set point"),
    Service("set_unit_parameters", SetUnitParameters, "PackTags parameters"),
    Service("set_product", SetProduct, "PackTags products"),
    Service("set_recipe", SetRecipe, "change the recipe: a changeover across the EMs",
            "changing recipes"),
    Service("set_em_active", SetEmActive, "switch an EM active or inactive (ModuleActive)",
            "switching equipment modules"),
    Service("set_interlock", SetInterlock, "a line interlock from outside (suspends the unit)"),
    Service("set_remote_commands", SetRemoteCommands,
            "the remote lock (remote_commands_enabled), from a local source only"),
    *SHORTCUTS,
)  # fmt: skip

TOPIC: Mapping[str, Topic] = {t.name: t for t in TOPICS}
#: The unit's topics its EMs follow (besides publishing its inputs): the unit's state.
EM_FOLLOWS: tuple[str, ...] = ("status", "recipe")
SERVICE: Mapping[str, Service] = {s.name: s for s in SERVICES}


def topics(*roles: Role) -> tuple[Topic, ...]:
    """The topics of ``roles`` (default all), in declaration order."""
    return tuple(t for t in TOPICS if not roles or t.role in roles)


def create_publisher(node: Node, name: str, *, lease: float | None = None, **kwargs: Any) -> Any:
    """The unit's publisher of topic ``name`` on ``node`` (the unit's own node): its declared type
    and QoS; ``lease`` (seconds) for a topic published with DDS liveliness."""
    topic = TOPIC[name]
    if topic.role is Role.INPUT:
        raise ValueError(f"{name} is an input of the unit: its EMs publish it")
    profile = qos.with_lease(topic.qos, lease) if topic.leased and lease is not None else topic.qos
    return node.create_publisher(topic.type, topic.path(), profile, **kwargs)


def create_service(node: Node, name: str, callback: Any, **kwargs: Any) -> Any:
    """The unit's service ``name`` on ``node`` behind the request boundary
    (:func:`packml_ros2.responses.create_service`)."""
    service = SERVICE[name]
    return responses.create_service(node, service.type, f"~/{name}", callback, **kwargs)


def create_services(
    node: Node,
    handlers: Mapping[str, Callable[[Any, Any], Any]],
    trigger: Callable[[Cmd, Any, Any], Any],
    lacking: Callable[[str, Any, Any], Any] | None = None,
    *,
    skip: Iterable[str] = (),
    **kwargs: Any,
) -> None:
    """Every declared service on ``node`` (a unit or a PLC bridge): ``handlers[name]``, the
    Trigger shortcuts by ``trigger(command, request, response)``; with ``lacking`` (a PLC
    bridge), the services it lacks by ``lacking(what, request, response)``. ``skip``: the ones
    the node serves otherwise (the remote lock's). A declared service without a handler is a
    ValueError: a node cannot silently miss one."""
    skipped = set(skip)
    for service in SERVICES:
        if service.name in skipped:
            continue
        if service.command is not None:
            handler: Callable[[Any, Any], Any] = partial(trigger, service.command)
        elif lacking is not None and service.plc_lacks:
            handler = partial(lacking, service.plc_lacks)
        elif service.name in handlers:
            handler = handlers[service.name]
        else:
            raise ValueError(f"{node.get_name()} has no handler for service {service.name}")
        create_service(node, service.name, handler, **kwargs)


def describe() -> str:
    """The interface as text (``unit_node --help``; names relative to the unit)."""
    lines = ["Services (relative to the unit's node, e.g. /demo_cell/robot_cell/command):"]
    lines += [f"  {s.name:<22} {s.type_name:<42} {s.doc}" for s in SERVICES]
    lines.append("Topics:")
    for t in TOPICS:
        how = "subscribed" if t.role is Role.INPUT else "published"
        lines.append(f"  {t.name:<22} {t.type_name:<42} {how}: {t.doc}")
    return "\n".join(lines)
