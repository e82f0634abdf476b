"""Issue 24 item 5: a unit killed (SIGKILL) in Execute and restarted. Its StopReason is the crash
(unplanned), not the planned stop before it (4006 "STOP by remote:mes" was kept, so the line booked
the restart downtime as planned and "unit restarted" appeared as planned and as unplanned); and the
Execute time since its last save survives (it was lost: up to the persistence period). Unit and
coordinator processes, killed for real."""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import pytest
from packml_interfaces.msg import CellStatus, LineLosses

from packml_ros2 import qos
from packml_ros2.core import Cmd, State
from packml_ros2.core.durable import TIME_CHECKPOINT
from packml_ros2.core.numbers import Mode
from packml_ros2.core.stopreason import STOP_ID_CRASH, STOP_ID_REMOTE
from test.ros.cells import UnitClient, start_unit_process, write_cell

pytestmark = pytest.mark.ros

EXECUTE = int(Mode.PRODUCTION) * 18 + int(State.EXECUTE)


def _ns(stamp: Any) -> int:
    return int(stamp.sec) * 10**9 + int(stamp.nanosec)


def restarted_bookings(m: LineLosses) -> set[tuple[str, str]]:
    """(scope, bucket) of every loss reason that names the restart."""
    return {
        (s.scope or "line", b.bucket)
        for s in m.scopes
        for b in s.buckets
        if "unit restarted" in b.reason and b.nanoseconds > 0
    }


def test_a_unit_killed_in_execute_restarts_with_the_crash_as_stop_reason_and_its_time(
    ros: Any, processes: Any, tmp_path: Path
) -> None:
    # no periodic snapshot during the test (period 60 s): only the journal keeps the times
    units = {
        name: {
            "remote_commands_enabled": True,
            "admin_period": 0.5,
            "persistence": {"path": str(tmp_path / f"{name}.sqlite3"), "period": 60},
        }
        for name in ("filler", "packer")
    }
    cell_file, cell = write_cell(tmp_path, units, {"unit_lease": 1.0})
    doc = cell_file.read_text() + "line: {order: [filler, packer], publish_period: 0.5}\n"
    cell_file.write_text(doc)
    filler = start_unit_process(processes, cell_file, "filler")
    start_unit_process(processes, cell_file, "packer")
    processes.module("coordinator", "packml_ros2.coordinator_node", str(cell_file))
    cell_status = ros.subscribe(CellStatus, f"/{cell}/coordinator/status", qos.CELL_STATUS)
    losses = ros.subscribe(LineLosses, f"/{cell}/coordinator/line/losses", qos.LINE_LOSSES)
    cell_status.wait_for(lambda m: m.all_online and len(m.units) == 2, 30, "both units online")
    clients = {name: UnitClient(ros, cell, name) for name in units}
    for client in clients.values():
        client.ready()
    client = clients["filler"]

    # a planned stop first (a remote Stop: 4006), then production again
    for name, c in clients.items():
        assert c.trigger("reset").success, name
        c.wait_state("IDLE")
        assert c.trigger("start").success, name
        c.wait_state("EXECUTE")
    assert client.command(Cmd.STOP, "remote:mes").accepted
    client.wait_state("STOPPED")
    planned = client.admin.wait_for(lambda a: a.stop_reason.id == STOP_ID_REMOTE, 5, "4006")
    assert "remote:mes" in planned.stop_reason.message
    assert client.trigger("reset").success
    client.wait_state("IDLE")
    assert client.trigger("start").success
    entered = client.wait_entered("EXECUTE")
    # four whole seconds in Execute (the admin data says so), then SIGKILL
    client.admin.wait_for(lambda a: a.state_cumulative_time[EXECUTE] >= 4, 15, "4 s in Execute")
    killed_at = time.time()
    filler.kill()
    in_execute = killed_at - _ns(entered.stamp) / 1e9
    cell_status.wait_for(lambda m: "filler" in m.lost_units, 10, "filler lost")

    mark = len(cell_status)
    client.forget()
    start_unit_process(processes, cell_file, "filler")
    restart = client.transitions.wait_for(lambda t: t.trigger == t.TRIGGER_RESTART, 20, "restart")
    assert restart.to_state == State.STOPPED
    after = client.admin.wait_for(lambda a: True, 10, "admin data of the restarted unit")
    # why it stopped: the crash, not the remote Stop before it
    assert after.stop_reason_extent == 1
    assert after.stop_reason.id == STOP_ID_CRASH, (after.stop_reason.id, after.stop_reason.message)
    assert "without shutting down" in after.stop_reason.message
    # the Execute time up to the kill, less at most one checkpoint period (whole seconds)
    kept = after.state_cumulative_time[EXECUTE]
    assert math.floor(in_execute - TIME_CHECKPOINT - 0.5) <= kept <= in_execute + 1, (
        kept,
        in_execute,
    )

    # the line books the restart downtime as unplanned, and only so
    cell_status.wait_for(lambda m: m.all_online, 20, "filler online again", mark)
    since = len(losses)
    booked = losses.wait_for(
        lambda m: m.window == "lifetime" and ("filler", "unplanned_stop") in restarted_bookings(m),
        20, "the restart booked", since,
    )  # fmt: skip
    assert {b for s, b in restarted_bookings(booked)} == {"unplanned_stop"}, [
        (s.scope, b.bucket, b.reason) for s in booked.scopes for b in s.buckets
    ]
