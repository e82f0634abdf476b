"""packml_ros2/executors.py: a message DDS has received reaches its callback at once, while the
same executor also answers service calls (the harness, the CLI and the coordinator do both).

A server in a context of its own publishes a message from each service call it answers; the
node under test calls the service and takes the message. rclpy 9.1's MultiThreadedExecutor
delivered such messages 0.1 ms to 3 s after DDS received them (p50 about 200 ms on 2 cores)."""

from __future__ import annotations

import statistics
import threading
import time
from typing import Any

import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from std_msgs.msg import String
from std_srvs.srv import Trigger

from packml_ros2.executors import MultiThreadedExecutor, spin_in_thread

pytestmark = pytest.mark.ros
CALLS = 40


def test_a_message_reaches_its_callback_while_service_calls_are_answered(ros_domain: int) -> None:
    contexts = [Context(), Context()]
    for c in contexts:
        rclpy.init(context=c, domain_id=ros_domain)
    base = f"/executor_probe_{threading.get_ident() % 100000}"
    server = Node("probe_server", context=contexts[0])
    news = server.create_publisher(String, f"{base}/news", 10)

    def answer(_request: Any, response: Any) -> Any:
        news.publish(String(data="answered"))
        response.success = True
        return response

    server.create_service(Trigger, f"{base}/ping", answer)
    user = Node("probe_user", context=contexts[1])
    late: list[float] = []
    arrived = threading.Condition()

    def on_news(_msg: String, info: Any) -> None:
        with arrived:
            late.append(time.time() - info["received_timestamp"] / 1e9)
            arrived.notify_all()

    user.create_subscription(String, f"{base}/news", on_news, 10)
    client = user.create_client(Trigger, f"{base}/ping")
    executors = [SingleThreadedExecutor(context=contexts[0]),
                 MultiThreadedExecutor(num_threads=4, context=contexts[1])]  # fmt: skip
    threads = [spin_in_thread(e, n) for e, n in zip(executors, (server, user), strict=True)]
    try:
        assert client.wait_for_service(timeout_sec=30)
        # the subscription matched: one answer's message arrives (discovery, not timed)
        deadline = time.monotonic() + 30
        while not late and time.monotonic() < deadline:
            client.call(Trigger.Request(), timeout_sec=10)
            with arrived:
                arrived.wait_for(lambda: bool(late), 0.5)
        assert late, "the subscription never matched"
        late.clear()
        for i in range(CALLS):
            assert client.call(Trigger.Request(), timeout_sec=10).success
            with arrived:
                assert arrived.wait_for(lambda n=i: len(late) > n, 10), f"message {i} never came"
    finally:
        for e in executors:
            e.shutdown(timeout_sec=5)
        for c in contexts:
            rclpy.try_shutdown(context=c)
        for t in threads:
            t.join(5)
    ms = sorted(x * 1000 for x in late)
    # measured: p50 0.1-0.3 ms here, against about 200 ms (max 3 s) with rclpy's executor
    assert statistics.median(ms) < 20 and ms[-1] < 1000, ms
