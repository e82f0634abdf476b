"""Recordings without nodes: drive an engine exactly as the unit node does (the same
:class:`~packml_ros2.driver.UnitDriver`, the ``start`` input, the start-up admin data) and write
what the node would have published into a bag — for benchmarks and tests of the replay itself.

    sim = SyntheticUnit(config, cell_yaml, start=1.7e9)
    sim.call(2.0, sim.unit.command, Cmd.RESET)      # an input at t = start + 2 s
    sim.write("out_bag")
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from rclpy.serialization import serialize_message

from .. import convert
from ..core import Unit, UnitConfig, inputlog
from ..core.liveliness import Liveliness
from ..driver import FrozenClock, UnitDriver
from .topics import (
    CUSTOM_KEY,
    OUTPUT_TOPICS,
    PUBLISHER_QOS,
    UNIT_TOPICS,
    close_writer,
    msg_class,
    open_writer,
    rosbags_qos,
    typestore,
)


class SyntheticUnit:
    """An engine driven like ``UnitNode``; its input log and outputs become a bag."""

    def __init__(
        self,
        config: UnitConfig,
        cell_yaml: str | None = None,
        start: float = 1.7e9,
        document: dict[str, Any] | None = None,
        persistence: bool = False,
    ) -> None:
        self.config = config
        self.prefix = f"/{config.cell}/{config.name}" if config.cell else f"/{config.name}"
        self.cell_yaml = cell_yaml
        self.now = start
        self.clock = FrozenClock(lambda: self.now)
        self.clock.frozen = start
        store = _Store(document) if persistence or document is not None else None
        persistence = store is not None
        self.unit = Unit(config, clock=self.clock, store=store)  # type: ignore[arg-type]
        self.clock.frozen = None
        self.start = self.unit.now
        self.liveliness = Liveliness(config.em_lease)
        #: topic -> [(time, serialized message)]
        self.messages: dict[str, list[tuple[float, bytes]]] = {t: [] for t in UNIT_TOPICS}
        self._index = 0
        self.unit.on_input = self._on_input
        self.driver = UnitDriver(self.unit, self.clock, self._emit)
        start_args = {
            "document": self.unit.restored,
            "time": self.unit.now,
            "persistence": persistence,
            "schema": inputlog.SCHEMA,
        }
        self._on_input(self.unit.now, inputlog.START, start_args)
        self.driver.flush()
        self._emit("admin", self.driver.admin_message())

    def _emit(self, topic: str, msg: Any) -> None:
        if topic in OUTPUT_TOPICS:
            self.messages[topic].append((self.now, serialize_message(msg)))

    def _on_input(self, t: float, name: str, args: dict[str, Any]) -> None:
        self._index += 1
        msg = msg_class(UNIT_TOPICS["input_log"])(
            stamp=convert.stamp(t),
            index=self._index,
            unit=self.config.name,
            name=name,
            args_json=json.dumps(args, separators=(",", ":")),
        )
        self.messages["input_log"].append((t, serialize_message(msg)))

    def advance(self, t: float) -> None:
        """Let time pass to ``start + t``: deadlines fire one at a time, as the node's timer does;
        EMs whose lease ran out are lost."""
        until = self.start + t
        unit = self.unit
        live = self.liveliness
        for name, lease in sorted(live.expired(until), key=lambda x: live.last_seen[x[0]] + x[1]):
            self.advance(live.last_seen[name] + lease - self.start)
            self.driver.call(self.now, unit.em_lost, name, f"no report for {lease:g} s")
        nxt = unit.next_deadline()
        while nxt is not None and nxt <= until:
            self.now = nxt
            self.driver.catch_up(nxt)
            nxt = unit.next_deadline()
        self.now = max(self.now, until)

    def call(self, t: float, fn: Callable[..., Any], *args: Any) -> Any:
        """Apply an input (a Unit method) at ``start + t``."""
        self.advance(t)
        return self.driver.call(self.now, fn, *args)

    def report(self, t: float, em: str, kind: int, **fields: Any) -> None:
        """An EM report at ``start + t`` (recorded on ``em_reports``), applied as the node does."""
        self.advance(t)
        cls = msg_class(UNIT_TOPICS["em_reports"])
        msg = cls(stamp=convert.stamp(self.now), em=em, kind=kind, lease=1.0, **fields)
        self.messages["em_reports"].append((self.now, serialize_message(msg)))
        self.driver.report(self.now, msg, self.liveliness)

    def snapshot(self) -> None:
        """The unit node's answer to a recorder joining now: its engine state on ``snapshot``."""
        published = {t: len(self.messages[t]) for t in OUTPUT_TOPICS}
        msg = self.driver.snapshot_message(self._index, published, self.unit.store is not None)
        self.messages["snapshot"].append((self.now, serialize_message(msg)))

    def write(
        self,
        path: str | os.PathLike[str],
        storage: str = "mcap",
        joined: float | None = None,
        stop: float | None = None,
    ) -> int:
        """Write the bag (outputs stamped at the time they were published); returns its size in
        messages. ``joined`` (seconds after the start): what a recorder that joined then has —
        the history the publishers keep (:data:`HISTORY`) and everything after; ``stop``: when it
        stopped (it has the outputs published before, and notes the time)."""
        writer = open_writer(Path(path), storage)
        store = typestore()
        items: list[tuple[int, int, Any, bytes]] = []
        order = 0
        if self.cell_yaml is not None and not self.messages["config"]:
            text = json.dumps({"unit": self.config.name, "cell_yaml": self.cell_yaml})
            self.messages["config"].append(
                (self.start, serialize_message(msg_class(UNIT_TOPICS["config"])(data=text)))
            )
        since = None if joined is None else self.start + joined
        until = None if stop is None else self.start + stop
        publications = {}
        for name, msgs in self.messages.items():
            conn = writer.add_connection(
                f"{self.prefix}/{name}",
                UNIT_TOPICS[name],
                typestore=store,
                offered_qos_profiles=[rosbags_qos(PUBLISHER_QOS[name])],
            )
            numbers = list(range(len(msgs)))
            if since is not None:  # the publishers' history, then what came after
                before = [i for i in numbers if msgs[i][0] < since]
                numbers = before[len(before) - HISTORY[name] :] + numbers[len(before) :]
            if until is not None and name != "input_log":
                numbers = [i for i in numbers if msgs[i][0] < until]
            for i in numbers:
                t, raw = msgs[i]
                items.append((round(max(t, since or t) * 1e9), order, conn, raw))
                order += 1
            if name in OUTPUT_TOPICS and numbers:
                publications[f"{self.prefix}/{name}"] = _ranges(n + 1 for n in numbers)
        items.sort(key=lambda x: (x[0], x[1]))
        last = 0
        for ts, _, conn, raw in items:
            last = max(ts, last + 1)
            writer.write(conn, last, raw)
        notes: dict[str, Any] = {
            "version": 2,
            "recorder": "packml_ros2.bag.synthetic",
            "publications": publications,
        }
        if until is not None:
            notes["stopped_at_ns"] = round(until * 1e9)
        writer.set_custom_data(CUSTOM_KEY, json.dumps(notes, separators=(",", ":")))
        close_writer(writer)
        return len(items)


#: Messages a publisher keeps for a subscriber that joins late (packml_ros2.qos), per topic.
HISTORY = {"input_log": 5000, "transitions": 100, "em_reports": 0, "config": 1, "status": 1,
           "admin": 1, "alarms": 1, "snapshot": 1, "recipe": 1, "stack_light": 1}  # fmt: skip


def _ranges(numbers: Iterable[int]) -> list[list[int]]:
    """[[first, last], ...] of runs of consecutive numbers."""
    out: list[list[int]] = []
    for n in numbers:
        if out and out[-1][1] + 1 == n:
            out[-1][1] = n
        else:
            out.append([n, n])
    return out


class _Store:
    def __init__(self, document: dict[str, Any] | None) -> None:
        self.document = document

    def load(self) -> dict[str, Any] | None:
        return self.document

    def save(self, document: dict[str, Any], now: float) -> None:
        pass

    def close(self) -> None:
        pass
