"""``packml record``: a recorder node writing a unit's (or a cell's) topics into a rosbag2 bag.

Per unit ``/<cell>/<unit>`` it subscribes (raw CDR, no decoding) to the inputs ``input_log``,
``em_reports``, ``config``, ``snapshot`` and the outputs ``status``, ``transitions``, ``admin``,
``alarms``; for a cell also ``/<cell>/coordinator/status`` and its line's ``line/input_log``,
``line/snapshot`` and the outputs ``line/episodes`` and ``line/losses`` (kept up to the stop and
numbered as the units' outputs are). Subscriptions take the publishers'
durability, so a recorder started after the unit still gets the last 5000 inputs (transient
local), the latest status, admin data, alarm list and the last 100 transitions — and the unit
publishes a snapshot of its engine state when the recorder's subscription joins, from which a
replay starts when the unit had applied more inputs than that.

Bag timestamps are receive times (strictly increasing in the bag's order). The bag stores the
publishers' QoS and every type definition (mcap by default, sqlite3 on request), readable by
rosbag2 and other tools. ``custom_data`` (metadata.yaml) key ``packml`` holds the recorder's notes:
the DDS publication sequence numbers of the recorded output messages (replay aligns on them
exactly) and the stop time.

Stopping (Ctrl-C, SIGTERM or ``--duration``) at time T: the bag holds exactly the outputs the units
stamped before T (their clock is this host's), so replay compares everything up to T. The
subscriptions stay open for :data:`DRAIN` seconds more: a unit publishes what a deadline due
before T caused at its next 50 ms tick, and its input log in batches (every 50 ms), so every
output stamped before T and every input behind it reach the bag; outputs stamped at or after T
are left out.
"""

from __future__ import annotations

import concurrent.futures
import itertools
import json
import os
import queue
import threading
import time
from collections.abc import Callable, Iterable
from functools import partial
from pathlib import Path
from typing import Any

from . import line
from .cdr import raw_stamp
from .topics import (
    CELL_STATUS_TYPE,
    CUSTOM_KEY,
    LATCHED_OUTPUTS,
    OUTPUT_TOPICS,
    PUBLISHER_QOS,
    STORAGES,
    UNIT_TOPICS,
    close_writer,
    msg_class,
    open_writer,
    reader_qos,
    rosbags_qos,
    typestore,
)

#: Seconds the subscriptions stay open after a stop (a unit publishes at its 50 ms ticks; a loaded
#: host delays them).
DRAIN = 1.0


class Recorder:
    """Records ``units`` (``/<cell>/<unit>`` paths) and the coordinator status of ``cells`` into
    a new bag at ``path``. Spin :attr:`node` (any executor); :meth:`stop`, then :meth:`close`."""

    def __init__(
        self,
        path: str | os.PathLike[str],
        units: Iterable[str],
        cells: Iterable[str] = (),
        *,
        storage: str = "mcap",
        context: Any = None,
        node_name: str | None = None,
    ) -> None:
        from ..boundary import GuardedNode as Node

        if storage not in STORAGES:
            raise ValueError(f"storage {storage!r}: choose one of {', '.join(STORAGES)}")
        self.path = Path(path)
        self.units = [u.rstrip("/") for u in units]
        self.cells = list(cells)
        # One thread owns the writer (sqlite3 objects stay in the thread that made them) and
        # does the disk I/O, so subscription callbacks only queue what they received.
        self._io = _WriterThread()
        self.writer = self._io.call(open_writer, self.path, storage)
        self.node = Node(node_name or f"packml_recorder_{os.getpid()}", context=context)
        self.counts: dict[str, int] = {}
        self.stopped_at: int | None = None  # ns (receive-time clock) when stop() was called
        self._last_ts = 0
        self._pubs: dict[str, list[list[int]]] = {}  # output topic -> publication ranges
        self._gids: dict[str, Any] = {}
        self._several: set[str] = set()
        self._closed = False
        self._lock = threading.Lock()  # callbacks may run on executor threads; close() too
        store = typestore()
        for prefix in self.units:
            for name, type_name in UNIT_TOPICS.items():
                self._add(f"{prefix}/{name}", name, type_name, store, name in OUTPUT_TOPICS)
        for cell in self.cells:
            topic = f"/{cell.strip('/')}/coordinator/status"
            self._add(topic, "coordinator", CELL_STATUS_TYPE, store, False)
            for topic, kind, type_name in line.topics(cell):  # its line's inputs and outputs
                name = topic.split("/coordinator/", 1)[1]
                output = name in line.LINE_OUTPUTS  # (kept up to the stop as the units')
                self._add(
                    topic,
                    kind,
                    type_name,
                    store,
                    output,
                    line.stamp_reader(name) if output else raw_stamp,
                )

    def _add(
        self,
        topic: str,
        kind: str,
        type_name: str,
        store: Any,
        output: bool,
        stamp: Callable[[bytes], float] = raw_stamp,
    ) -> None:
        conn = self._io.call(
            partial(
                self.writer.add_connection,
                topic,
                type_name,
                typestore=store,
                offered_qos_profiles=[rosbags_qos(PUBLISHER_QOS[kind])],
            )
        )
        self.counts[topic] = 0
        callback: Callable[[bytes, Any], None] = partial(
            self._on_message,
            topic,
            conn,
            kind in ("input_log", "line_input_log"),
            stamp if output else None,
        )
        self.node.create_subscription(
            msg_class(type_name), topic, callback, reader_qos(kind), raw=True
        )

    # -- receiving ---------------------------------------------------------------------------------
    def _on_message(
        self,
        topic: str,
        conn: Any,
        input_log: bool,
        output: Callable[[bytes], float] | None,
        raw: bytes,
        info: Any,
    ) -> None:
        """``output``: the stamp reader of an output topic (None: not an output)."""
        received = int(info.get("received_timestamp") or time.time_ns())
        with self._lock:
            if self._closed:
                return
            stopped = self.stopped_at
            if stopped is not None and not input_log:
                # outputs: what was stamped before the stop (the unit's clock); others: what
                # arrived before it
                when = output(raw) * 1e9 if output is not None else received
                if not when < stopped:
                    return
            ts = max(received, self._last_ts + 1)
            self._last_ts = ts
            self._io.post(self.writer.write, conn, ts, raw)
            self.counts[topic] += 1
            if output is not None:
                self._note_publication(topic, info)

    def _note_publication(self, topic: str, info: Any) -> None:
        seq = info.get("publication_sequence_number")
        gid = info.get("publisher_gid")
        if topic in self._several:
            return
        if seq is None:
            self._several.add(topic)  # the middleware does not tell: replay aligns by content
            return
        known = self._gids.setdefault(topic, gid)
        if known != gid:
            self._several.add(topic)  # a second publisher (the unit restarted): by content
            return
        ranges = self._pubs.setdefault(topic, [])
        if ranges and ranges[-1][1] + 1 == seq:
            ranges[-1][1] = seq
        else:
            ranges.append([seq, seq])

    # -- state -------------------------------------------------------------------------------------
    def received(self, topic: str) -> int:
        return self.counts.get(topic, 0)

    def unit_ready(self, unit: str) -> bool:
        """The unit's latched outputs (status, admin, alarms: a unit publishes each at its start)
        have arrived: the recorder is matched on every one of them, not only on the first. A
        recording that began earlier could miss the admin data or alarm list published before
        it, and a replay would then see them as outputs the unit did not publish."""
        return all(self.received(f"{unit}/{topic}") > 0 for topic in LATCHED_OUTPUTS)

    def ready(self) -> bool:
        """Every recorded unit's latched outputs have arrived (the recorder is matched)."""
        return all(self.unit_ready(u) for u in self.units)

    def lost(self) -> dict[str, int]:
        """Output messages the recorder missed (gaps in the publication sequence numbers)."""
        out = {}
        for topic, ranges in self._pubs.items():
            gaps = sum(b[0] - a[1] - 1 for a, b in itertools.pairwise(ranges))
            if gaps:
                out[topic] = gaps
        return out

    def stop(self) -> None:
        """Stop recording now: outputs stamped from now on are left out, the subscriptions stay
        open for what was stamped before (see :data:`DRAIN`)."""
        if self.stopped_at is None:
            self.stopped_at = time.time_ns()

    def close(self) -> Path:
        """Write the bag's index and metadata.yaml (idempotent); returns the bag's path."""
        with self._lock:
            if self._closed:
                return self.path
            self.stop()
            self._closed = True
        notes = {
            "version": 1,
            "recorder": "packml_ros2",
            "units": self.units,
            "stopped_at_ns": self.stopped_at,
            "publications": {
                topic: ranges for topic, ranges in self._pubs.items() if topic not in self._several
            },
        }
        self._io.call(
            self.writer.set_custom_data, CUSTOM_KEY, json.dumps(notes, separators=(",", ":"))
        )
        self._io.call(close_writer, self.writer)
        self._io.stop()
        self.node.destroy_node()
        return self.path


class _WriterThread:
    """Runs the bag writer's calls in order on one thread."""

    def __init__(self) -> None:
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="packml-bag-writer", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            fn, args, future = item
            try:
                result = fn(*args)
            except BaseException as exc:  # reported to the caller, or kept for the next call
                if future is not None:
                    future.set_exception(exc)
                elif self.error is None:
                    self.error = exc
                continue
            if future is not None:
                future.set_result(result)

    def post(self, fn: Callable[..., Any], *args: Any) -> None:
        self._queue.put((fn, args, None))

    def call(self, fn: Callable[..., Any], *args: Any) -> Any:
        future: concurrent.futures.Future[Any] = concurrent.futures.Future()
        self._queue.put((fn, args, future))
        result = future.result()
        if self.error is not None:
            error, self.error = self.error, None
            raise error
        return result

    def stop(self) -> None:
        self._queue.put(None)
        self._thread.join()


def run_recorder(
    recorder: Recorder,
    executor: Any,
    should_stop: Callable[[], bool],
    duration: float | None = None,
    drain: float = DRAIN,
    announce: Callable[[str], None] | None = None,
) -> None:
    """Spin until ``should_stop()`` or ``duration`` seconds, then drain the input log and close.
    ``announce(unit)`` is called once the unit's latched outputs have arrived."""
    deadline = None if duration is None else time.monotonic() + duration
    waiting = list(recorder.units)
    while not should_stop() and (deadline is None or time.monotonic() < deadline):
        executor.spin_once(timeout_sec=0.05)
        if waiting and announce is not None:
            for unit in [u for u in waiting if recorder.unit_ready(u)]:
                waiting.remove(unit)
                announce(unit)
    recorder.stop()
    end = time.monotonic() + drain
    while time.monotonic() < end:
        executor.spin_once(timeout_sec=0.02)
    recorder.close()
