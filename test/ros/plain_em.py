"""An equipment module in plain rclpy: one subscription, one publisher, timers. No packml_ros2
import: it follows docs/em-protocol.md as an EM in another language (rclcpp) would.

Usage: ``python plain_em.py <cell> <unit> <em> [work seconds] [cycle seconds] [lease seconds]``.
Every acting state takes ``work`` seconds; Execute counts one processed product per ``cycle``
and runs until commanded. Ctrl-C (SIGINT): a goodbye (KIND_LEAVE), then exit 0.
"""

from __future__ import annotations

import signal
import sys
import time

import rclpy
from packml_interfaces.msg import EmReport, Status
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions

ACTING = {Status.STATE_RESETTING, Status.STATE_STARTING, Status.STATE_EXECUTE,
          Status.STATE_COMPLETING, Status.STATE_HOLDING, Status.STATE_UNHOLDING,
          Status.STATE_SUSPENDING, Status.STATE_UNSUSPENDING, Status.STATE_STOPPING,
          Status.STATE_ABORTING, Status.STATE_CLEARING}  # fmt: skip
STATUS_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL)  # fmt: skip
REPORTS_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=200,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)  # fmt: skip


class PlainEm(Node):
    def __init__(self, cell: str, unit: str, em: str, work: float, cycle: float, lease: float):
        super().__init__(em, namespace=f"/{cell}/{unit}")
        self.em, self.work, self.cycle, self.lease = em, work, cycle, lease
        self.pub = self.create_publisher(EmReport, "em_reports", REPORTS_QOS)
        self.create_subscription(Status, "status", self.on_status, STATUS_QOS)
        self.create_timer(lease / 4, self.heartbeat)
        self.working_on: tuple[int, int] | None = None
        self.reported: tuple[int, int] | None = None
        self.reported_at = 0.0  # time.monotonic() of the last State Complete
        self.latest: Status | None = None
        self.timer = None  # the work of the current state (one shot) or Execute's cycle
        self.heartbeat()

    def send(self, kind: int, **fields: object) -> None:
        msg = EmReport(em=self.em, kind=kind, lease=self.lease, **fields)
        msg.stamp = self.get_clock().now().to_msg()
        self.pub.publish(msg)

    def heartbeat(self) -> None:
        self.send(EmReport.KIND_HEARTBEAT)
        # retransmission: reported for the current pair a quarter-lease ago, and the unit has
        # not taken it yet
        s = self.latest
        due = time.monotonic() - self.reported_at >= self.lease / 4
        if s is not None and due and self.reported == (s.state_current, s.sequence):
            mine = self.mine(s)
            if mine is not None and not mine.state_complete:
                self.complete()

    def mine(self, s: Status):  # type: ignore[no-untyped-def]
        return next((e for e in s.equipment_modules if e.name == self.em), None)

    def on_status(self, s: Status) -> None:
        self.latest = s
        key = (s.state_current, s.sequence)
        if key == self.working_on:
            return
        mine = self.mine(s)
        if mine is not None and (not mine.active or mine.state_complete):
            return
        self.working_on = key
        if self.timer is not None:  # the unit left the state: the work stops
            self.destroy_timer(self.timer)
            self.timer = None
        if s.unit_mode_change_in_process:
            self.complete()
        elif s.state_current == Status.STATE_EXECUTE:
            self.timer = self.create_timer(self.cycle, self.produce)
        elif s.state_current in ACTING:
            self.timer = self.create_timer(self.work, self.done)

    def produce(self) -> None:
        self.send(EmReport.KIND_COUNT, counter=EmReport.COUNTER_PROCESSED, increment=1)

    def done(self) -> None:
        if self.timer is not None:
            self.destroy_timer(self.timer)
            self.timer = None
        self.complete()

    def complete(self) -> None:
        assert self.working_on is not None
        state, sequence = self.working_on
        self.reported = self.working_on
        self.reported_at = time.monotonic()
        self.send(EmReport.KIND_STATE_COMPLETE, state=state, sequence=sequence)


def main() -> int:
    cell, unit, em, *rest = sys.argv[1:]
    work, cycle, lease = ([float(x) for x in rest] + [0.1, 0.2, 2.0][len(rest) :])[:3]
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    node = PlainEm(cell, unit, em, work, cycle, lease)
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        node.send(EmReport.KIND_LEAVE)
        node.pub.wait_for_all_acked(Duration(seconds=2))  # delivered before the writer goes
        print(f"EM {em} left unit {unit} (SIGINT)", flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
