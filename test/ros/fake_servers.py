"""A robot's existing ROS 2 drivers, for the tests of action/service EMs (packml_ros2.interface_em):
a move action server (``test_msgs/action/Fibonacci``) and a gripper service (``std_srvs/srv/SetBool``),
in plain rclpy, in a process of its own (so a test can kill it mid-goal and start it again).

Usage: ``python fake_servers.py <action name> <service name> [step seconds]``.

The move: a goal of ``order`` n runs n steps of ``step`` seconds, a feedback message per step
(the sequence so far), and succeeds with the first n Fibonacci numbers (mod 1000); order < 0 is rejected;
order >= 1000 aborts after its first step; a cancel request ends it at the next step (canceled).
Each goal's end is printed (``goal <n> succeeded|canceled|aborted``), and ``client seen`` once this
process has discovered the reply readers of an action client's goal and result requests: a plain
rclpy server drops its answer to a client it has not discovered yet (Fast DDS waits 100 ms), so a
test that restarts the servers under a running EM waits for that line before the EM's next goal.
The gripper: ``data: true`` succeeds; ``data: false`` answers ``success: false`` ("jaws jammed").
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
import time

import rclpy
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from std_srvs.srv import SetBool
from test_msgs.action import Fibonacci

from packml_ros2.executors import MultiThreadedExecutor


class Drivers(Node):
    def __init__(self, action: str, service: str, step: float) -> None:
        super().__init__("fake_drivers")
        self.step = step
        group = ReentrantCallbackGroup()
        self.server = ActionServer(
            self, Fibonacci, action, self.execute, callback_group=group,
            goal_callback=self.on_goal, cancel_callback=lambda _: CancelResponse.ACCEPT,
        )  # fmt: skip
        self.create_service(SetBool, service, self.grip, callback_group=group)

    def on_goal(self, goal: Fibonacci.Goal) -> GoalResponse:
        return GoalResponse.REJECT if goal.order < 0 else GoalResponse.ACCEPT

    def execute(self, handle):  # type: ignore[no-untyped-def]
        order = handle.request.order
        sequence = [0, 1][: max(order, 0)]
        for i in range(max(order, 1)):
            if handle.is_cancel_requested:
                handle.canceled()
                print(f"goal {order} canceled", flush=True)
                return Fibonacci.Result(sequence=sequence)
            time.sleep(self.step)  # the robot moving
            if order >= 1000:
                handle.abort()
                print(f"goal {order} aborted", flush=True)
                return Fibonacci.Result()
            if i >= 2:
                sequence.append((sequence[-1] + sequence[-2]) % 1000)  # (fits int32)
            handle.publish_feedback(Fibonacci.Feedback(sequence=sequence[: i + 1]))
        handle.succeed()
        print(f"goal {order} succeeded", flush=True)
        return Fibonacci.Result(sequence=sequence[:order])

    def grip(self, req: SetBool.Request, resp: SetBool.Response) -> SetBool.Response:
        resp.success = bool(req.data)
        resp.message = "gripped" if req.data else "jaws jammed"
        return resp


def main() -> int:
    action, service, *rest = sys.argv[1:]
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    node = Drivers(action, service, float(rest[0]) if rest else 0.1)
    executor = MultiThreadedExecutor(num_threads=4)
    executor.add_node(node)
    print("drivers ready", flush=True)

    def watch_clients() -> None:
        replies = [f"rr{node.resolve_topic_name(action)}/_action/{s}Reply" for s in ("send_goal", "get_result")]  # fmt: skip
        while rclpy.ok():
            try:
                if all(node.get_subscriptions_info_by_topic(r, no_mangle=True) for r in replies):
                    print("client seen", flush=True)
                    return
            except Exception:  # the node shut down meanwhile
                return
            time.sleep(0.05)

    threading.Thread(target=watch_clients, daemon=True).start()
    with contextlib.suppress(KeyboardInterrupt):
        executor.spin()
    executor.shutdown(timeout_sec=2)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
