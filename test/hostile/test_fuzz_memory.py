"""Issue 25 item 14: after 12 000 fuzzed requests a unit held 452 MB (96 MB before). The fuzz of
test_ros_requests.py, against a unit node running as its own process (with a simulated EM, the
remote lock holding): the memory of that process, settled after a warm-up and again after the
fuzz, stays within 20 % of where it was; every request is answered and refused, and the unit
publishes nothing (no status, no transition, no alarm list).

The resident set (VmRSS) is read from /proc; "settled": polled until it has not fallen for a
while (freed memory goes back to the system late, if at all), so a peak of the fuzz that is
given back is not counted and one that is kept is.

Measured here: +11 % after the fuzz, most of it the buffers of the service request readers
(Fast DDS keeps, in each slot of a reader's history, a buffer the size of the largest sample it
held); the second test sends only the fuzz's longest strings and finds +54 % (xfail until the
readers free their buffers: with that, +3.6 % and +0.8 %)."""

from __future__ import annotations

import copy
import random
import time
from pathlib import Path
from typing import Any

import pytest
from packml_interfaces.msg import Result as R
from packml_interfaces.srv import SetAlarm, SetInterlock, SetMode

from packml_ros2.testing.processes import Processes
from test.hostile.test_ros_requests import (
    BATCH,
    SEED,
    UNIT_DOC,
    all_refused,
    hostile,
    pipelined,
    rss_mb,
)
from test.ros.cells import UnitClient, write_cell

pytestmark = pytest.mark.ros

COUNT = 12_000  # the figure: ~30 s here (2-2.5 ms a request, a process each side)
WARM_UP = 600  # every kind of request has been met (clients, caches, the limiter's kinds)
MAX_GROWTH = 0.20  # of the settled RSS after the warm-up
SETTLE_QUIET = 2.0  # s: settled when the RSS has not fallen for this long ...
SETTLE_MAX = 15.0  # ... or after this long


def settled_rss(pid: int, quiet: float = SETTLE_QUIET, bound: float = SETTLE_MAX) -> float:
    """The lowest RSS (MB) of process ``pid`` once it has stopped falling: sampled every 0.1 s
    until no new low for ``quiet`` seconds (at most ``bound`` seconds in all)."""
    start = low_at = time.monotonic()
    low = rss_mb(pid)
    while (now := time.monotonic()) - low_at < quiet and now - start < bound:
        time.sleep(0.1)
        sample = rss_mb(pid)
        if sample < low:
            low, low_at = sample, time.monotonic()
    return low


def fuzz(ros: Any, unit: UnitClient, requests: Any, count: int,
         clients: dict[tuple[Any, str], Any], counts: dict[int, int]) -> None:  # fmt: skip
    """Send ``count`` requests, pipelined ``BATCH`` at a time: each is answered and refused with
    a reason it may have."""
    sent = 0
    while sent < count:
        batch = [next(requests) for _ in range(min(BATCH, count - sent))]
        all_refused(pipelined(ros, clients, unit.base, batch), counts)
        sent += len(batch)


def start_unit(ros: Any, processes: Processes, tmp_path: Path) -> tuple[Any, UnitClient, Any]:
    """The unit of ``UNIT_DOC`` and its EM, each a process; the unit's process, a client, and
    its status with the EM online."""
    cell_file, cell = write_cell(tmp_path, {"u": copy.deepcopy(UNIT_DOC)})
    unit_process = processes.module("unit", "packml_ros2.unit_node", str(cell_file), "u")
    processes.module("em_nozzle", "packml_ros2.sim_em", str(cell_file), "u", "nozzle")
    unit = UnitClient(ros, cell, "u")
    unit.ready(30)
    status = unit.wait_status(
        lambda s: [(e.name, e.online) for e in s.equipment_modules] == [("nozzle", True)],
        30, "the EM online",
    )  # fmt: skip
    assert not status.remote_commands_enabled, "the fuzz expects the remote lock to hold"
    return unit_process, unit, status


def test_a_unit_process_gives_back_the_memory_of_a_fuzz(
    ros: Any, processes: Processes, tmp_path: Path
) -> None:
    unit_process, unit, before = start_unit(ros, processes, tmp_path)
    marks = (len(unit.status), len(unit.transitions), len(unit.alarms))
    clients: dict[tuple[Any, str], Any] = {}
    requests = hostile(random.Random(SEED))
    counts: dict[int, int] = {}
    fuzz(ros, unit, requests, WARM_UP, clients, counts)
    rss_before = settled_rss(unit_process.pid)

    started = time.monotonic()
    fuzz(ros, unit, requests, COUNT, clients, counts)
    elapsed = time.monotonic() - started
    peak = rss_mb(unit_process.pid)
    rss_after = settled_rss(unit_process.pid)
    log_bytes = len(unit_process.output())
    print(
        f"\n{COUNT} hostile requests in {elapsed:.1f} s ({1000 * elapsed / COUNT:.2f} ms each) "
        f"after {WARM_UP} to warm up; unit RSS {rss_before:.1f} MB settled before, "
        f"{peak:.1f} MB at the end, {rss_after:.1f} MB settled after "
        f"({100 * (rss_after - rss_before) / rss_before:+.1f} %); unit log {log_bytes} bytes; "
        f"results {dict(sorted(counts.items()))}"
    )

    assert unit_process.running(), unit_process.output()[-3000:]
    assert sum(counts.values()) == WARM_UP + COUNT, counts
    published = (len(unit.status), len(unit.transitions), len(unit.alarms))
    assert published == marks, f"(status, transitions, alarms) published {marks} -> {published}"
    after = unit.status.last
    assert (after.state_current, after.unit_mode_current, after.mach_speed) == (
        before.state_current, before.unit_mode_current, before.mach_speed)  # fmt: skip
    assert [(e.name, e.online) for e in after.equipment_modules] == [("nozzle", True)]
    assert not after.remote_commands_enabled
    assert rss_after <= rss_before * (1 + MAX_GROWTH), (
        f"the unit's RSS grew from {rss_before:.1f} to {rss_after:.1f} MB after {COUNT} requests"
    )


OVERSIZED = 100_000  # characters: the longest string of the fuzz (long_text)
ROUNDS = 3  # pipelined batches per service


@pytest.mark.xfail(
    strict=True,
    reason="issue 25 item 14: rmw_fastrtps gives each service's request reader the history "
    "memory policy PREALLOCATED_WITH_REALLOC: every slot of its history (qos.SERVICES: 256) keeps "
    "a buffer the size of the largest request it held, for the life of the process",
)
def test_oversized_requests_leave_no_memory_behind(
    ros: Any, processes: Processes, tmp_path: Path
) -> None:
    """The retention the fuzz above only grazes: requests of the fuzz's longest string, pipelined
    ``BATCH`` at a time to three services. Each is refused at the boundary, after DDS has taken
    it in whole: the buffers DDS took it into must be given back. rmw_fastrtps gives every
    reader the history memory policy PREALLOCATED_WITH_REALLOC, where each slot of a service's
    history (qos.SERVICES: 256) kept a buffer the size of the largest request it held, for the
    life of the process (+19 MB a service here, +54 % in all). Giving readers DYNAMIC in our
    Fast DDS profiles (with RMW_FASTRTPS_USE_QOS_FROM_XML=1) passed this test (+1.1 %) but
    three DDS tests of a fresh-clone run then lost statuses and a service answer: not yet."""
    unit_process, unit, _ = start_unit(ros, processes, tmp_path)
    clients: dict[tuple[Any, str], Any] = {}
    requests = hostile(random.Random(SEED))
    counts: dict[int, int] = {}
    fuzz(ros, unit, requests, WARM_UP, clients, counts)
    rss_before = settled_rss(unit_process.pid)
    bad = {R.INVALID_ARGUMENT}
    started = time.monotonic()
    for srv, name, field in ((SetMode, "set_mode", "mode_name"),
                             (SetInterlock, "set_interlock", "reason"),
                             (SetAlarm, "set_alarm", "message")):  # fmt: skip
        batch = [(srv, name, {field: "y" * OVERSIZED}, bad)] * BATCH
        fuzz(ros, unit, iter(batch * ROUNDS), BATCH * ROUNDS, clients, counts)
    elapsed = time.monotonic() - started
    rss_after = settled_rss(unit_process.pid)
    print(
        f"\n{3 * ROUNDS * BATCH} requests of {OVERSIZED} characters in {elapsed:.1f} s; unit RSS "
        f"{rss_before:.1f} MB settled before, {rss_after:.1f} MB settled after "
        f"({100 * (rss_after - rss_before) / rss_before:+.1f} %)"
    )
    assert unit_process.running(), unit_process.output()[-3000:]
    assert rss_after <= rss_before * (1 + MAX_GROWTH), (
        f"the unit's RSS grew from {rss_before:.1f} to {rss_after:.1f} MB"
    )
