"""rclpy in the test process: a fresh Context per test, nodes spun by a multi-threaded executor
in a background thread, and helpers that wait on conditions instead of sleeping."""

from __future__ import annotations

import threading
import time
import traceback
from collections.abc import Callable
from typing import Any, Generic, TypeVar

import rclpy
from rclpy.context import Context
from rclpy.event_handler import QoSSubscriptionMatchedInfo, SubscriptionEventCallbacks
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile

from ..executors import MultiThreadedExecutor

M = TypeVar("M")


class Collector(Generic[M]):
    """Messages of one subscription, with waiting. A wait that times out says how many writers
    the subscription had matched and how many the graph held (:meth:`RosHarness.subscribe`):
    a writer seen but never matched is a discovery that went one way, one matched that sent
    nothing a writer or a transport that failed."""

    def __init__(
        self, graph: Callable[[], int] | None = None, again: Callable[[], None] | None = None
    ) -> None:
        self.messages: list[M] = []
        self._cond = threading.Condition()
        self.matched = 0  #: writers matched now (the subscription's matched event)
        self._graph = graph  # writers of the topic in the graph
        #: a latched topic's new subscription in place of the old one (once; see wait_for)
        self._again = again
        self.resubscribed = False

    def on_matched(self, info: QoSSubscriptionMatchedInfo) -> None:
        self.matched = info.current_count

    def _writers(self) -> str:
        try:
            graph = self._graph() if self._graph is not None else "?"
        except Exception:  # the node is gone: the count is what is missing, not the message
            graph = "?"
        return f"writers matched {self.matched}, in the graph {graph}"

    def __call__(self, msg: M) -> None:
        with self._cond:
            self.messages.append(msg)
            self._cond.notify_all()

    def __len__(self) -> int:
        with self._cond:
            return len(self.messages)

    @property
    def last(self) -> M:
        with self._cond:
            return self.messages[-1]

    def wait_for(
        self, predicate: Callable[[M], bool], timeout: float = 10.0, what: str = "", start: int = 0
    ) -> M:
        """The first message (already received or coming) for which ``predicate`` holds, looking
        at messages from index ``start`` on (``len(collector)`` before an action: only newer ones).
        A latched topic's subscription that has received nothing half way through the wait,
        while a writer is on the graph, is replaced by a new one, once: a reader DDS never
        served the latched sample stays deaf (seen in CI), a new one takes it at once."""
        now = time.monotonic()
        deadline, again_at = now + timeout, now + timeout / 2
        seen = start
        while True:
            with self._cond:
                while True:
                    for msg in self.messages[seen:]:
                        if predicate(msg):
                            return msg
                    seen = len(self.messages)
                    now = time.monotonic()
                    if now >= deadline:
                        tail = self.messages[-3:]
                        raise TimeoutError(
                            f"no message {what or 'matching'} within {timeout:g} s "
                            f"({self._writers()}); last: {tail}"
                        )
                    if self._again is not None and not self.messages and now >= again_at:
                        break
                    wake = deadline if self._again is None or self.messages else again_at
                    self._cond.wait(wake - now)
            again_at = deadline  # (outside the lock: the executor's thread may be waiting on it)
            if self._graph is not None and self._graph() > 0:
                again, self._again = self._again, None
                if again is not None:
                    again()
                    self.resubscribed = True

    def wait_count(self, n: int, timeout: float = 10.0) -> list[M]:
        deadline = time.monotonic() + timeout
        with self._cond:
            while len(self.messages) < n:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TimeoutError(f"{len(self.messages)} of {n} messages within {timeout:g} s")
                self._cond.wait(remaining)
            return list(self.messages)

    def clear(self) -> None:
        with self._cond:
            self.messages.clear()


def servers_of(node: Node, service: str) -> int:
    """How many servers of ``service`` (a full name: ``/cell/unit/reset``, an action's
    ``.../_action/send_goal``) ``node``'s graph holds: their request readers. A SIGKILLed server
    stays there for its participant's lease; a client sees it as ready meanwhile, and a request
    sent then can miss the server started in its place."""
    return len(node.get_subscriptions_info_by_topic(f"rq{service}Request", no_mangle=True))


def wait_server_gone(node: Node, service: str, timeout: float = 30.0) -> None:
    """Until no server of ``service`` is left in ``node``'s graph (one that was killed)."""
    deadline = time.monotonic() + timeout
    while servers_of(node, service):
        if time.monotonic() > deadline:
            raise TimeoutError(f"a server of {service} still in the graph after {timeout:g} s")
        time.sleep(0.05)


class RosHarness:
    """Nodes of one test on their own Context (domain ``domain``)."""

    def __init__(self, domain: int, threads: int = 4) -> None:
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.executor = MultiThreadedExecutor(num_threads=threads, context=self.context)
        self.node = Node(f"test_harness_{threading.get_ident() % 100000}", context=self.context)
        self.executor.add_node(self.node)
        self._nodes: list[Node] = [self.node]
        self.errors: list[str] = []
        self._closing = False
        self._thread = threading.Thread(target=self._spin, name="ros-harness", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        """Spin until shutdown. A callback that raises would end ``spin()`` and silently stop
        every node of the test: record the error (``errors``; checked at close) and go on."""
        while self.context.ok():
            try:
                self.executor.spin()
                return
            except (ExternalShutdownException, rclpy.executors.ShutdownException):
                return
            except Exception as exc:
                if self._closing and (
                    "after shutdown" in str(exc)
                    or "destruction was requested" in str(exc)
                    or not self.context.ok()
                ):
                    # rclpy 9.1 at shutdown: MultiThreadedExecutor.shutdown closes its thread pool
                    # while spin() may still hand it a callback ("cannot schedule new futures
                    # after shutdown", ros2/rclpy#1724), or spin() builds one more wait set on the
                    # context being shut down ("the given context is not valid", #968): the end
                    # of the test, not an error of one of its callbacks. So is a handler of a
                    # callback that ran during shutdown triggering the executor's guard condition
                    # shutdown() destroyed ("destruction was requested": rclpy 9.1 catches that
                    # InvalidHandle after the callback, not at its start).
                    return
                self.errors.append("".join(traceback.format_exception(exc)))

    def add(self, node: Node) -> Node:
        """Spin ``node`` (created with ``context=harness.context``) until the test ends."""
        self.executor.add_node(node)
        self._nodes.append(node)
        return node

    def subscribe(self, msg_type: type[M], topic: str, qos: QoSProfile | int = 10) -> Collector[M]:
        """A subscription's messages; a latched one (transient local) is replaced by a new one
        when a wait finds it deaf (:meth:`Collector.wait_for`)."""
        subs: list[Any] = []

        def make() -> None:
            subs.append(
                self.node.create_subscription(
                    msg_type,
                    topic,
                    collector,
                    qos,
                    event_callbacks=SubscriptionEventCallbacks(matched=collector.on_matched),
                )
            )

        def again() -> None:
            make()
            self.node.destroy_subscription(subs.pop(0))

        latched = isinstance(qos, QoSProfile) and qos.durability == DurabilityPolicy.TRANSIENT_LOCAL
        collector: Collector[M] = Collector(
            lambda: self.node.count_publishers(topic), again if latched else None
        )
        make()
        return collector

    def call(self, srv_type: Any, name: str, request: Any = None, timeout: float = 10.0) -> Any:
        """Call service ``name`` (waiting for it to appear first) and return the response."""
        client = self._clients.get((srv_type, name)) if hasattr(self, "_clients") else None
        if client is None:
            client = self.node.create_client(srv_type, name)
            self.__dict__.setdefault("_clients", {})[(srv_type, name)] = client
        if not client.wait_for_service(timeout_sec=timeout):
            raise TimeoutError(f"service {name} did not appear within {timeout:g} s")
        future = client.call_async(request if request is not None else srv_type.Request())
        done = threading.Event()
        future.add_done_callback(lambda _: done.set())
        if not done.wait(timeout):
            raise TimeoutError(f"service {name} did not answer within {timeout:g} s")
        return future.result()

    def ask(
        self,
        srv_type: Any,
        name: str,
        request: Any = None,
        timeout: float = 10.0,
        every: float = 2.0,
    ) -> Any:
        """Like :meth:`call`, for a request that may be sent again (a query): sent once more every
        ``every`` seconds until one answer comes, within ``timeout``. A server started a moment ago
        (a restart) is in the graph before this client's request writer has matched it, and a
        request written then is lost: DDS services are volatile."""
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            try:
                return self.call(srv_type, name, request, min(every, max(left, 0.1)))
            except TimeoutError:
                if time.monotonic() + 0.1 >= deadline:
                    raise TimeoutError(
                        f"service {name} did not answer within {timeout:g} s"
                    ) from None

    def wait_for_service(self, srv_type: Any, name: str, timeout: float = 10.0) -> None:
        client: Any = self.node.create_client(srv_type, name)
        try:
            if not client.wait_for_service(timeout_sec=timeout):
                raise TimeoutError(f"service {name} did not appear within {timeout:g} s")
        finally:
            self.node.destroy_client(client)

    def close(self) -> None:
        """Shut down; raises if a callback failed during the test."""
        self._closing = True
        self.executor.shutdown(timeout_sec=5)
        for node in self._nodes:
            node.destroy_node()
        rclpy.try_shutdown(context=self.context)
        self._thread.join(5)
        if self.errors:
            raise AssertionError("a callback raised during the test:\n" + "\n".join(self.errors))
