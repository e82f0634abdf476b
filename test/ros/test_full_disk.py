"""Issue 25 item 2: a full disk under the stores. Real unit and coordinator processes whose
stores live on a small tmpfs this test mounts and fills: they run on, raise the
``persistence_failing`` alarm, say in their answers that they are not durable, recover when space
returns, and a unit started on the full disk keeps its store (never moved aside as unreadable)."""

from __future__ import annotations

import contextlib
import errno
import os
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
from packml_interfaces.msg import CellStatus
from packml_interfaces.srv import Command, SetMachSpeed

from packml_ros2 import qos
from packml_ros2.core import Cmd
from packml_ros2.testing.processes import Processes, wait_until
from test.ros.cells import UnitClient, start_unit_process, write_cell

FAILING = 9005  # SystemAlarms.persistence_failing


@pytest.fixture
def disk(tmp_path: Path) -> Iterator[Path]:
    """A 1 MB tmpfs: the stores' file system, which the test fills."""
    where = tmp_path / "disk"
    where.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(where)],
                             capture_output=True, text=True, check=False)  # fmt: skip
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs (needs root): {mounted.stderr.strip()}")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], check=False)


def fill(disk: Path) -> Path:
    """Write a file until the file system is full (ENOSPC)."""
    filler = disk / "filler"
    with filler.open("wb", buffering=0) as f:
        for _ in range(10_000):  # (1 MB in 4 KB writes, bounded)
            try:
                f.write(b"x" * 4096)
            except OSError as exc:
                assert exc.errno == errno.ENOSPC
                break
        else:
            raise AssertionError("the tmpfs did not fill")
        with contextlib.suppress(OSError):  # the last bytes of a partly used page
            while f.write(b"x"):
                pass
    return filler


def _failing(alarms: object) -> bool:
    """Whether the ``persistence_failing`` alarm is active in an AlarmList."""
    return any(a.id == FAILING and a.trigger for a in alarms.alarms)  # type: ignore[attr-defined]


def _not_durable_until_failing(client: UnitClient) -> str:
    """Change the speed until an answer says it is not durable (the journal's last page may
    hold a few records more after the disk filled up); its message."""
    for n in range(1, 2000):
        resp = client.call(SetMachSpeed, "set_mach_speed", mach_speed=float(100 + n % 7))
        assert resp.accepted, resp.message
        if "not durable" in resp.message:
            return str(resp.message)
    raise AssertionError("no answer said it was not durable on a full disk")


def test_a_full_disk_keeps_the_cell_running_raises_an_alarm_and_recovers(
    ros, processes: Processes, tmp_path: Path, disk: Path
) -> None:
    units = {name: {"mach_speed": 50.0, "remote_commands_enabled": True, "persistence": {"path": str(disk / "{unit}.sqlite3"), "period": 0.5}}
             for name in ("filler", "packer")}  # fmt: skip
    cell_file, cell = write_cell(tmp_path, units)
    procs = [start_unit_process(processes, cell_file, name) for name in units]
    coordinator = processes.module("coordinator", "packml_ros2.coordinator_node", str(cell_file))
    procs.append(coordinator)
    filler, packer = UnitClient(ros, cell, "filler"), UnitClient(ros, cell, "packer")
    cell_status = ros.subscribe(CellStatus, f"/{cell}/coordinator/status", qos.CELL_STATUS)
    for client in (filler, packer):
        client.ready(30)
    cell_status.wait_for(lambda m: m.all_online and len(m.units) == 2, 30, "both units online")
    resp = filler.call(SetMachSpeed, "set_mach_speed", mach_speed=77.0)
    assert resp.accepted and "not durable" not in resp.message, resp.message

    filler_file = fill(disk)
    message = _not_durable_until_failing(filler)
    assert "filler.sqlite3" in message, message  # which file, and why
    filler.alarms.wait_for(_failing, 10, "the alarm")
    # the cell works on: commands through the coordinator reach both units, whose line store
    # cannot take the losses either
    for cmd, state in ((Cmd.RESET, "IDLE"), (Cmd.START, "EXECUTE"), (Cmd.STOP, "STOPPED")):
        request = Command.Request(command=int(cmd), source="operator")
        answer = ros.call(Command, f"/{cell}/coordinator/command", request, 30)
        assert answer.accepted, answer.message
        for client in (filler, packer):
            client.wait_state(state)
    cell_status.wait_for(lambda m: "not durable" in m.detail, 10, "the cell status says so")
    assert all(p.running() for p in procs), [p.output()[-2000:] for p in procs if not p.running()]
    assert "persistence failing" in coordinator.output()

    since = len(filler.alarms)
    filler_file.unlink()  # space returns: the next try (each second) succeeds, the alarm clears
    filler.alarms.wait_for(lambda m: not _failing(m), 10, "cleared", since)
    resp = filler.call(SetMachSpeed, "set_mach_speed", mach_speed=88.0)
    assert resp.accepted and "not durable" not in resp.message, resp.message
    assert filler.command(Cmd.RESET).accepted
    cell_status.wait_for(lambda m: "not durable" not in m.detail, 10, "the line store recovered")
    wait_until(lambda: "persistence recovered" in coordinator.output(), 10, what="coordinator recovered")  # fmt: skip
    assert all(p.running() for p in procs)
    for p in procs:
        assert p.stop() == 0, p.output()[-3000:]
    assert not [f.name for f in disk.iterdir() if "unreadable" in f.name]


def test_a_unit_started_on_a_full_disk_keeps_its_store(
    ros, processes: Processes, tmp_path: Path, disk: Path
) -> None:
    store = disk / "filler.sqlite3"
    units = {"filler": {"mach_speed": 50.0, "persistence": {"path": str(store)}}}
    cell_file, cell = write_cell(tmp_path, units)
    unit = start_unit_process(processes, cell_file, "filler")
    client = UnitClient(ros, cell, "filler")
    client.ready(30)
    assert client.call(SetMachSpeed, "set_mach_speed", mach_speed=66.0).accepted
    assert client.command(Cmd.RESET).accepted
    client.wait_state("IDLE")
    assert unit.stop() == 0, unit.output()

    filler_file = fill(disk)
    client.forget()
    unit = start_unit_process(processes, cell_file, "filler")
    client.ready(30)
    status = client.wait_status(lambda s: True, 10)
    assert status.mach_speed == 66.0, unit.output()  # the admin data as stored
    admin = client.admin.wait_for(lambda a: True, 10)
    assert any("unit restarted" in a.message for a in admin.alarm_history), admin.alarm_history
    client.alarms.wait_for(_failing, 10, "the alarm")
    assert not [f.name for f in disk.iterdir() if "unreadable" in f.name], os.listdir(disk)
    resp = client.command(Cmd.RESET)
    assert resp.accepted and "not durable" in resp.message, resp.message
    client.wait_state("IDLE")

    since = len(client.alarms)
    filler_file.unlink()
    client.alarms.wait_for(lambda m: not _failing(m), 10, "cleared", since)
    assert unit.stop() == 0, unit.output()
    client.forget()
    unit = start_unit_process(processes, cell_file, "filler")
    client.ready(30)
    assert client.wait_status(lambda s: True, 10).mach_speed == 66.0
    assert not [f.name for f in disk.iterdir() if "unreadable" in f.name], os.listdir(disk)
    assert unit.stop() == 0, unit.output()
