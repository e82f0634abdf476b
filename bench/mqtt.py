"""MQTT benchmark: how long after a unit's state changes a Sparkplug host application sees it in
a DDATA, against the floor of a bare publish through the same broker, in the same run; and how
many messages per second per unit the edge node sends at rest.

A unit (no EMs: every acting state completes at once) and ``packml mqtt`` run as processes,
Debian's mosquitto on a free 127.0.0.1 port. This process commands Hold / Unhold over ROS, and
takes the time each status reaches its own ROS subscription and the time the DDATA carrying that
state reaches its own MQTT subscriber. The edge node receives the same status at the same moment
(one DDS hop both), so the difference is what the edge adds plus one broker hop: that is set
against the floor, a payload of a DDATA's size published by this process to itself through the
same broker after each change (interleaved: under the same load). ``unit_to_ddata`` is the
whole path from the unit's status stamp. Prints JSON.

    python bench/mqtt.py [--changes 200] [--rest 10]

Everything stays on this machine (loopback, a ROS domain of its own).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
GOAL_RATIO = 1.5


def pct(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(q * (len(ordered) - 1)))]


def summary(values: list[float]) -> dict[str, float]:
    return {"p50": round(statistics.median(values), 3), "p99": round(pct(values, 0.99), 3),
            "max": round(max(values), 3)}  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    parser.add_argument("--changes", type=int, default=200, help="state changes measured")
    parser.add_argument("--rest", type=float, default=10.0, help="seconds counted at rest")
    args = parser.parse_args()

    from packml_ros2.testing.environment import allocate_domain, localhost_environment

    localhost_environment()
    os.environ["ROS_DOMAIN_ID"] = str(allocate_domain())
    import paho.mqtt.client as paho
    from packml_interfaces.msg import Status
    from packml_interfaces.srv import Command

    from packml_ros2 import qos
    from packml_ros2.core import Cmd
    from packml_ros2.testing.harness import RosHarness
    from packml_ros2.testing.processes import Processes
    from test.mqtt.host import Broker

    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        broker = Broker(tmp)
        cell = f"mqttbench{os.getpid()}"
        doc = {"cell": cell, "units": {"filler": {"remote_commands_enabled": True,
                                                   "persistence": {"path": str(tmp / "{unit}.sqlite3")}}},
               "coordinator": {"enabled": False},
               "mqtt": {"port": broker.port, "client_id": "bench-edge"}}  # fmt: skip
        path = tmp / "cell.yaml"
        path.write_text(yaml.safe_dump(doc, sort_keys=False))
        procs = Processes(tmp)
        ros = RosHarness(int(os.environ["ROS_DOMAIN_ID"]))
        lock = threading.Condition()
        ros_at: list[tuple[int, float, float]] = []  # state, received (s), unit's stamp (s)
        mqtt_at: list[tuple[int, float]] = []  # state, received (s)
        floor_at: dict[int, float] = {}
        messages: list[float] = []
        alias: dict[int, str] = {}

        def on_status(msg: Any) -> None:
            now = time.time()
            with lock:
                if not ros_at or ros_at[-1][0] != msg.state_current:
                    ros_at.append((msg.state_current, now, msg.stamp.sec + msg.stamp.nanosec / 1e9))
                lock.notify_all()

        def on_message(client: Any, userdata: Any, m: Any) -> None:
            now = time.time()
            if m.topic == "bench/floor":
                with lock:
                    floor_at[int.from_bytes(m.payload[:4], "little")] = now
                    lock.notify_all()
                return
            with lock:
                messages.append(now)
            kind = m.topic.split("/")[2]
            if kind not in ("DBIRTH", "DDATA"):
                return
            for named, number, value in _metrics(m.payload):
                if kind == "DBIRTH" and named:
                    alias[number] = named
                name = named or alias.get(number or -1)
                if name == "State/Current":
                    with lock:
                        mqtt_at.append((value, now))
                        lock.notify_all()

        ros.node.create_subscription(Status, f"/{cell}/filler/status", on_status, qos.STATUS)
        sub = paho.Client(client_id="bench-host")
        sub.on_message = on_message
        sub.connect("127.0.0.1", broker.port)
        sub.subscribe([("spBv1.0/#", 0), ("bench/floor", 0)])
        sub.loop_start()
        pub = paho.Client(client_id="bench-floor")
        pub.connect("127.0.0.1", broker.port)
        pub.loop_start()
        try:
            procs.module("unit", "packml_ros2.unit_node", str(path), "filler")
            procs.module("mqtt", "packml_ros2.cli.main", "mqtt", str(path))
            wait(lock, lambda: any(s == 2 for s, _ in mqtt_at), 60, "the unit born, Stopped")

            def command(cmd: Cmd, state: int) -> None:
                answer = ros.call(Command, f"/{cell}/filler/command",
                                  Command.Request(command=int(cmd), source="operator:bench"), 30)  # fmt: skip
                assert answer.accepted, answer.message
                n = len(mqtt_at)
                wait(lock, lambda: any(s == state for s, _ in mqtt_at[n:]) or mqtt_at[-1][0] == state, 30, str(state))  # fmt: skip

            command(Cmd.RESET, 4)
            command(Cmd.START, 6)
            first = (len(ros_at), len(mqtt_at))
            floor: list[float] = []

            def bare_publish() -> None:
                """The floor, interleaved with the changes (the same load around it): a payload
                of a DDATA's size, this process to itself through the same broker."""
                i = len(floor)
                sent = time.time()
                pub.publish("bench/floor", i.to_bytes(4, "little") + b"x" * 120, qos=0)
                wait(lock, lambda: i in floor_at, 10, "the floor message")
                floor.append((floor_at[i] - sent) * 1000)

            for _ in range(args.changes // 2):
                command(Cmd.HOLD, 11)
                bare_publish()
                command(Cmd.UNHOLD, 6)
                bare_publish()
            # at rest: Stopped, nothing commanded
            command(Cmd.STOP, 2)
            time.sleep(2.0)  # let the stop's own messages pass before counting
            rest_from = time.time()
            time.sleep(args.rest)  # counting what arrives in a fixed window is the measurement
            with lock:
                at_rest = sum(1 for t in messages if t >= rest_from) / args.rest
        finally:
            sub.loop_stop()
            pub.loop_stop()
            ros.close()
            procs.close()
            broker.kill()

    # the wait states (Held, Execute) of each cycle, in order, in both streams: acting states can
    # be passed over by either subscription (it keeps the latest status), a wait state cannot
    def waits(seen: list[Any]) -> list[Any]:
        out: list[Any] = []
        for item in seen:
            if item[0] in (6, 11) and (not out or out[-1][0] != item[0]):
                out.append(item)
        return out

    changes = list(zip(waits(ros_at[first[0] :]), waits(mqtt_at[first[1] :]), strict=False))
    assert all(r[0] == m[0] for r, m in changes), "the wait states came in another order"
    edge_ms = [(m[1] - r[1]) * 1000 for r, m in changes]
    whole_ms = [(m[1] - r[2]) * 1000 for r, m in changes]
    out = {
        "changes": len(changes),
        "status_to_ddata_ms": summary(edge_ms),
        "floor_bare_publish_ms": summary(floor),
        "ratio_p50": round(statistics.median(edge_ms) / statistics.median(floor), 2),
        "ratio_p99": round(pct(edge_ms, 0.99) / pct(floor, 0.99), 2),
        "goal_ratio": GOAL_RATIO,
        "unit_to_ddata_ms": summary(whole_ms),
        "messages_per_s_per_unit_at_rest": round(at_rest, 2),
        "rest_window_s": args.rest,
    }
    print(json.dumps(out, indent=1))


def _metrics(raw: bytes) -> list[tuple[str, int, Any]]:
    """(name, alias, value) of each metric, read as a host application reads them (Eclipse Tahu's
    protobuf, as the tests do): a birth carries more metrics than the edge takes in a command, so
    the edge's own bounded decoder is not the reader here."""
    from google.protobuf.message import DecodeError

    from test.mqtt.host import Payload, metric_value

    payload = Payload()
    try:
        payload.ParseFromString(raw)
    except DecodeError:
        return []
    return [(m.name, m.alias, metric_value(m)) for m in payload.metrics]


def wait(cond: threading.Condition, predicate: Any, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    with cond:
        while not predicate():
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"no {what} within {timeout:g} s")
            cond.wait(left)


if __name__ == "__main__":
    main()
