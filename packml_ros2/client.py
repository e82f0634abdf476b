"""Talking to PackML units from other programs: the ``packml`` command line, the cell coordinator,
the HMI backend and the OPC UA bridge all use :class:`UnitProxy` / :class:`CellProxy`.

A proxy subscribes to a unit's latched topics (status, admin, alarms) and calls its services
asynchronously. It never blocks an executor thread: ``call`` returns a future, ``call_sync`` waits
on it from a thread that is not spinning the node.
"""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Callable, Iterable
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any

from packml_interfaces.msg import Admin, AlarmList, CellStatus, Status, TransitionEvent
from packml_interfaces.srv import Command, SetMode
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.node import Node

from . import qos
from .core.numbers import Cmd, parse_command
from .ros import interface

#: The unit services a proxy can call (:data:`.ros.interface.SERVICES`): name -> type.
SERVICES: dict[str, Any] = {s.name: s.type for s in interface.SERVICES}


class Unavailable(RuntimeError):
    """The unit (or cell) did not answer in time."""


def call_future(client: Any, request: Any, path: str) -> Future[Any]:
    """``client.call_async(request)`` as a concurrent.futures.Future, which any thread can wait
    on; failed at once with :class:`Unavailable` when the service ``path`` is not there."""
    result: Future[Any] = Future()
    if not client.service_is_ready():
        result.set_exception(Unavailable(f"{path} is not available"))
        return result

    def done(f: Any) -> None:
        exc = f.exception()
        if exc is not None:
            result.set_exception(exc)
        else:
            result.set_result(f.result())

    client.call_async(request).add_done_callback(done)
    return result


def call_blocking(client: Any, request: Any, timeout: float, path: str) -> Any:
    """Wait up to ``timeout`` for the service ``path`` to appear, call it and wait for the answer
    (from a thread that is not spinning the client's node); :class:`Unavailable` otherwise."""
    if not client.wait_for_service(timeout_sec=timeout):
        raise Unavailable(f"{path} is not available")
    try:
        return call_future(client, request, path).result(timeout)
    except TimeoutError:
        raise Unavailable(f"{path} did not answer within {timeout:g} s") from None


def resolve_unit(name: str, cell: str | None = None) -> str:
    """``/cell/unit`` from ``unit`` (with ``cell``), ``cell/unit`` or ``/cell/unit``."""
    name = name.strip()
    if name.startswith("/"):
        return name.rstrip("/")
    if "/" in name:
        return "/" + name.rstrip("/")
    if not cell:
        raise ValueError(f"unit {name!r} needs a cell: give cell/{name} or --cell")
    return f"/{cell}/{name}"


#: Seconds between a proxy's looks for a deaf reader (:meth:`UnitProxy.deaf`), and how many
#: times at most it subscribes again to a latched topic that never came while its writer is on
#: the graph.
DEAF_CHECK = 2.0
DEAF_TRIES = 3
LATCHED = ("status", "admin", "alarms")


@dataclass
class UnitProxy:
    """One unit (``path`` = ``/cell/unit``) seen from ``node``. While a followed latched topic
    has not arrived although its writer is on the graph, the proxy subscribes to it again every
    :data:`DEAF_CHECK` seconds (at most :data:`DEAF_TRIES` times): a reader that DDS never
    served the latched sample stays deaf, a new one takes it at once (seen in CI about once in
    4 600 tests; :mod:`.equipment_module` does the same)."""

    node: Node
    path: str
    on_change: Callable[[str, str, Any], None] | None = None  # (unit path, topic, msg)
    #: the topics to follow (default all): a short-lived tool that shows the status needs neither
    #: the transitions' 100-message history nor the alarm list
    topics: tuple[str, ...] = ("status", "admin", "alarms", "transitions")
    status: Status | None = None
    admin: Admin | None = None
    alarms: AlarmList | None = None
    status_received_at: float = 0.0
    transitions: list[TransitionEvent] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.name = self.path.rsplit("/", 1)[-1]
        self._group = ReentrantCallbackGroup()  # its service clients
        # Its topics, one message at a time: under a MultiThreadedExecutor (the coordinator's) a
        # reentrant group lets another thread take a topic's next message while the previous one
        # waits for the consumer's lock, and ``on_change`` then sees them out of order.
        self._topic_group = MutuallyExclusiveCallbackGroup()
        self._cond = threading.Condition()
        self._clients: dict[str, Any] = {}
        #: how each followed topic is taken in (its type and QoS: :mod:`.ros.interface`)
        self._callbacks: dict[str, Callable[[Any], None]] = {
            "status": self._on_status,
            "admin": self._on("admin"),
            "alarms": self._on("alarms"),
            "transitions": self._on_transition,
        }
        self._subs_lock = threading.Lock()  # (the deaf watch and a coordinator resubscribe)
        self._subs = {topic: self._subscribe(topic) for topic in self.topics}
        self._deaf_tries = 0
        self._deaf_timer: Any = None
        if any(t in LATCHED for t in self.topics):
            self._deaf_timer = self.node.create_timer(
                DEAF_CHECK, self._watch_deaf, callback_group=self._topic_group
            )

    def _subscribe(self, topic: str) -> Any:
        declared = interface.TOPIC[topic]
        return self.node.create_subscription(
            declared.type,
            declared.path(self.path),
            self._callbacks[topic],
            declared.qos,
            callback_group=self._topic_group,
            event_callbacks=qos.quiet_events(),
        )

    def resubscribe(self, *topics: str) -> None:
        """Subscribe again to latched topics (``status``, ``admin``, ``alarms``, ``transitions``;
        default: all): a new subscription receives the latest samples as soon as it is matched.
        Useful when a unit comes back after a network partition: the old subscription would get
        what it missed only by reliable repair, at the writer's next heartbeat (seconds).
        ``transitions`` then delivers its history again (up to 100 already seen ones)."""
        with self._subs_lock:
            for topic in topics or self.topics:
                old = self._subs.get(topic)
                self._subs[topic] = self._subscribe(topic)
                if old is not None:
                    self.node.destroy_subscription(old)

    def _watch_deaf(self) -> None:
        """The timer's look (one at a time with the topics' callbacks: the same group)."""
        latched = [t for t in LATCHED if t in self._subs]
        if self._deaf_tries >= DEAF_TRIES or all(getattr(self, t) is not None for t in latched):
            self._deaf_timer.cancel()
            return
        try:
            if self.hear_again(*latched):
                self._deaf_tries += 1
        except RuntimeError:  # (rclpy's InvalidHandle, RCLError) the node is being destroyed
            self._deaf_tries = DEAF_TRIES  # a tool that gave up and closes: nothing to watch

    def publishers(self, topic: str) -> int:
        """How many writers of a followed ``topic`` this proxy's subscription has matched."""
        sub = self._subs.get(topic)
        return 0 if sub is None else int(sub.get_publisher_count())

    # -- topics ------------------------------------------------------------------------------------
    def _on_status(self, msg: Status) -> None:
        with self._cond:
            self.status = msg
            self.status_received_at = time.monotonic()
            self._cond.notify_all()
        if self.on_change:
            self.on_change(self.path, "status", msg)

    def _on(self, attr: str) -> Callable[[Any], None]:
        def callback(msg: Any) -> None:
            with self._cond:
                setattr(self, attr, msg)
                self._cond.notify_all()
            if self.on_change:
                self.on_change(self.path, attr, msg)

        return callback

    def _on_transition(self, msg: TransitionEvent) -> None:
        with self._cond:
            self.transitions.append(msg)
            del self.transitions[:-100]
            self._cond.notify_all()
        if self.on_change:
            self.on_change(self.path, "transitions", msg)

    def wait_status(
        self, predicate: Callable[[Status], bool] = lambda s: True, timeout: float = 10.0
    ) -> Status:
        """Block (not in an executor thread) until the unit's status satisfies ``predicate``."""
        if not self._await(
            lambda: self.status is not None and predicate(self.status), "status", timeout
        ):
            state = self.status.state_current_name if self.status else "no status"
            raise Unavailable(f"{self.path}: condition not met within {timeout:g} s (now {state})")
        assert self.status is not None
        return self.status

    def wait_admin(self, timeout: float = 10.0) -> Admin:
        """Block (not in an executor thread) until the unit's admin data has arrived."""
        return self._wait_latched("admin", "admin data", timeout)

    def wait_alarms(self, timeout: float = 10.0) -> AlarmList:
        """Block (not in an executor thread) until the unit's (latched) alarm list has arrived."""
        return self._wait_latched("alarms", "alarm list", timeout)

    def _wait_latched(self, attr: str, what: str, timeout: float) -> Any:
        if not self._await(lambda: getattr(self, attr) is not None, attr, timeout):
            raise Unavailable(f"{self.path}: no {what} within {timeout:g} s")
        return getattr(self, attr)

    def _await(self, ready: Callable[[], bool], topic: str, timeout: float) -> bool:
        """Wait until ``ready()`` (checked under the lock) for at most ``timeout`` s. Half way,
        a latched ``topic`` that never arrived although its writer is on the graph is subscribed
        to again, once (as the deaf watch does, for waits shorter than its period)."""
        start = time.monotonic()
        deadline, again_at = start + timeout, start + timeout / 2
        while True:
            with self._cond:
                while not ready():
                    now = time.monotonic()
                    if now >= deadline:
                        return False
                    if again_at <= now:
                        break
                    self._cond.wait(min(deadline, again_at) - now)
                else:
                    return True
            again_at = float("inf")  # (outside the lock: a subscription takes the node's locks)
            self.hear_again(topic)

    def hear_again(self, *topics: str) -> bool:
        """Subscribe again to those of ``topics`` that are :meth:`deaf`; whether any was."""
        deaf = [t for t in topics if self.deaf(t)]
        if deaf:  # (none given, resubscribe() would take every topic)
            self.resubscribe(*deaf)
        return bool(deaf)

    def deaf(self, topic: str) -> bool:
        """Whether this proxy follows ``topic``, has never received it, and its writer is on
        the graph (whether or not this proxy's reader matched it)."""
        if topic not in self._subs or getattr(self, topic, None) is not None:
            return False
        return bool(self.node.count_publishers(interface.TOPIC[topic].path(self.path)))

    # -- services ----------------------------------------------------------------------------------
    def client(self, service: str) -> Any:
        if service not in self._clients:
            self._clients[service] = self.node.create_client(
                SERVICES[service],
                f"{self.path}/{service}",
                qos_profile=qos.SERVICES,  # requests pipelined by a face are never dropped
                callback_group=self._group,
            )
        return self._clients[service]

    def call(self, service: str, **fields: Any) -> Future[Any]:
        """Call ``service`` with request ``fields``; a concurrent.futures.Future of the response."""
        request = SERVICES[service].Request(**fields)
        return call_future(self.client(service), request, f"{self.path}/{service}")

    def call_sync(self, service: str, timeout: float = 10.0, **fields: Any) -> Any:
        """Wait for the service to appear, call it and wait for the answer (not from an executor
        thread of ``node``)."""
        client = self.client(service)
        if not client.wait_for_service(timeout_sec=timeout):
            raise Unavailable(f"{self.path}/{service} did not appear within {timeout:g} s")
        try:
            return self.call(service, **fields).result(timeout)
        except TimeoutError:
            raise Unavailable(
                f"{self.path}/{service} did not answer within {timeout:g} s"
            ) from None

    def command(
        self, cmd: int | str, source: str = "operator", timeout: float = 10.0
    ) -> Command.Response:
        number = int(parse_command(cmd)) if isinstance(cmd, str) else int(cmd)
        return self.call_sync("command", timeout, command=number, source=source)

    def set_mode(
        self, mode: int | str, source: str = "operator", timeout: float = 10.0
    ) -> SetMode.Response:
        if isinstance(mode, str) and not mode.isdigit():
            return self.call_sync("set_mode", timeout, mode_name=mode, source=source)
        return self.call_sync("set_mode", timeout, mode=int(mode), source=source)

    def destroy(self) -> None:
        if self._deaf_timer is not None:
            self._deaf_timer.cancel()
            self.node.destroy_timer(self._deaf_timer)
        for sub in self._subs.values():
            self.node.destroy_subscription(sub)
        for client in self._clients.values():
            self.node.destroy_client(client)


class CellProxy:
    """All units of a cell: from the configuration, or discovered on the ROS graph."""

    def __init__(
        self,
        node: Node,
        cell: str,
        units: Iterable[str] = (),
        on_change: Callable[[str, str, Any], None] | None = None,
        topics: tuple[str, ...] = UnitProxy.topics,
    ) -> None:
        self.node = node
        self.cell = cell
        self.on_change = on_change
        self.topics = topics  # what each unit's proxy follows
        self.units: dict[str, UnitProxy] = {}
        self.cell_status: CellStatus | None = None
        for unit in units:
            self.add(unit)
        self._cell_sub = node.create_subscription(
            CellStatus,
            f"/{cell}/coordinator/status",
            self._on_cell,
            qos.CELL_STATUS,
            event_callbacks=qos.quiet_events(),
        )

    def _on_cell(self, msg: CellStatus) -> None:
        self.cell_status = msg
        if self.on_change:
            self.on_change(f"/{self.cell}/coordinator", "cell_status", msg)

    def add(self, unit: str) -> UnitProxy:
        path = resolve_unit(unit, self.cell)
        name = path.rsplit("/", 1)[-1]
        if name not in self.units:
            self.units[name] = UnitProxy(self.node, path, self.on_change, self.topics)
        return self.units[name]

    def discover(self, timeout: float = 3.0, expect: int = 0) -> list[str]:
        """Add the units of this cell that appear on the graph, and every unit the coordinator's
        (latched) cell status lists (a lost unit too: a killed unit or a PLC that is gone has no
        status writer on the graph, but it is still a unit of the cell); returns their names. It
        stops as soon as the cell is complete: ``expect`` units known, or the coordinator's cell
        status arrived; without a coordinator, once no new unit has appeared for
        :data:`DISCOVERY_SETTLE` seconds; at the latest after ``timeout``."""
        deadline = time.monotonic() + timeout
        coordinator = f"/{self.cell}/coordinator/status"
        changed = time.monotonic()
        while True:
            graph = _graph_units(self.node)
            before = len(self.units)
            status = self.cell_status
            listed = (
                [u.name for u in status.units if _UNIT_NAME.fullmatch(u.name)]
                if status is not None
                else []
            )
            for unit in sorted({*graph.get(self.cell, ()), *listed}):
                self.add(unit)
            now = time.monotonic()
            if len(self.units) != before:
                changed = now
            if expect and len(self.units) >= expect:
                break
            if status is not None:
                break
            settled = self.units and now - changed >= DISCOVERY_SETTLE
            # a coordinator on the graph lists the cell's units: wait a little for its status
            if settled and (coordinator not in graph.topics or now - changed >= 1.0):
                break
            if now >= deadline:
                break
            time.sleep(0.02)
        return sorted(self.units)

    def unit(self, name: str) -> UnitProxy:
        path = resolve_unit(name, self.cell)
        key = path.rsplit("/", 1)[-1]
        if key not in self.units or self.units[key].path != path:
            return self.add(path)
        return self.units[key]


#: A unit name as a ROS node name (what a coordinator's cell status may add to a proxy).
_UNIT_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]{0,254}")

#: Graph discovery ends this long after the last new unit appeared (when no coordinator lists a
#: cell's units): the participants of a running cell all answer a newcomer's first announcement,
#: so their topics arrive together (config/fastdds_localhost.xml announces every 50 ms).
DISCOVERY_SETTLE = 0.15


class _Graph(dict[str, set[str]]):
    """``{cell: {unit, ...}}`` seen on the graph, and every topic name (``topics``)."""

    topics: set[str]


def _graph_units(node: Node) -> _Graph:
    found = _Graph()
    found.topics = set()
    for topic, types in node.get_topic_names_and_types():
        found.topics.add(topic)
        parts = topic.strip("/").split("/")
        if len(parts) == 3 and parts[2] == "status" and "packml_interfaces/msg/Status" in types:
            found.setdefault(parts[0], set()).add(parts[1])
    return found


def discover_cells(node: Node, timeout: float = 3.0, until: str = "") -> dict[str, list[str]]:
    """Cells and their units visible on the graph: ``{cell: [unit, ...]}``, once no new unit has
    appeared for :data:`DISCOVERY_SETTLE` seconds, or at once when every cell found has a
    coordinator (whose cell status lists its units: :meth:`CellProxy.discover` completes them);
    with ``until``, once a unit of that name is found (or the graph settled without it); at the
    latest after ``timeout``."""
    deadline = time.monotonic() + timeout
    found: dict[str, set[str]] = {}
    changed = time.monotonic()
    while True:
        graph = _graph_units(node)
        now = time.monotonic()
        if graph != found:
            found, changed = graph, now
        coordinated = all(f"/{cell}/coordinator/status" in graph.topics for cell in found)
        settled = bool(found) and now - changed >= DISCOVERY_SETTLE
        if until:
            done = settled or any(until in units for units in found.values())
        else:
            done = settled or (bool(found) and coordinated)
        if done or now >= deadline:
            return {cell: sorted(units) for cell, units in sorted(found.items())}
        time.sleep(0.02)


def command_number(text: str) -> int:
    """A command from a name (``start``) or a number (``2``); ValueError names the valid ones."""
    try:
        return int(parse_command(text))
    except ValueError as exc:
        raise ValueError(
            f"{exc} (commands: {', '.join(c.name.lower() for c in Cmd if c)})"
        ) from None
