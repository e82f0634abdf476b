"""Persistence (docs/packml.md §6): times, counters, alarm history, stop reason and the
sequence survive a restart; the state never does. A child process killed with SIGKILL at random
moments leaves a store that is intact and consistent."""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

import pytest

from packml_ros2.core import Cmd as C
from packml_ros2.core import Mode, Reason, State, Store, Trigger, Unit
from packml_ros2.core.stopreason import STOP_ID_CRASH, STOP_ID_REMOTE

from .helpers import FakeClock, cell_unit, transitions

S = State
PYTHON = sys.executable  # children run under the interpreter of this test run
UNIT = {
    "alarms": [{"id": 42, "message": "guard door", "category": 3}],
    "counters": {"processed": [{"id": 1, "name": "cartons"}]},
    "remote_commands_enabled": True,
}


def open_unit(path: Path, clock: FakeClock, **extra: Any) -> Unit:
    return Unit(cell_unit({**UNIT, **extra}), clock, Store(path, "u"))


def test_round_trip_restores_admin_never_the_state(tmp_path: Path) -> None:
    path = tmp_path / "u.sqlite3"
    clock = FakeClock(5_000.0)
    unit = open_unit(path, clock)
    clock.advance(10.0)
    assert unit.command(C.RESET).accepted and unit.command(C.START).accepted
    clock.advance(20.0)
    unit.em_count("em", "processed", 0, 7)
    assert unit.set_alarm(42).accepted and unit.state is S.STOPPED  # category 3: Stop
    assert unit.set_alarm(42, active=False).accepted
    assert unit.set_mode("maintenance").accepted
    assert unit.command(C.RESET).accepted and unit.command(C.START).accepted
    clock.advance(5.0)
    unit.advance()
    assert unit.state is S.EXECUTE and unit.mode == Mode.MAINTENANCE
    before = unit.admin()
    seq = unit.sequence
    history = [(e.id, e.message) for e in before.alarm_history]
    unit.close()

    clock.advance(100.0)  # down for 100 s: that time is not counted
    again = open_unit(path, clock)
    assert again.state is S.STOPPED  # never restored
    assert again.mode == Mode.PRODUCTION  # the configured initial mode
    assert again.sequence == seq + 1
    (tr,) = transitions(again)
    assert (tr.from_state, tr.to_state, tr.trigger, tr.sequence) == (
        S.STOPPED, S.STOPPED, Trigger.RESTART, seq + 1
    )  # fmt: skip
    after = again.admin()
    assert after.times.state_cumulative == before.times.state_cumulative
    assert after.times.mode_cumulative == before.times.mode_cumulative
    assert after.times.acc_time_since_reset == before.times.acc_time_since_reset == 35
    assert after.times.mode_current[Mode.PRODUCTION] == 0
    c = after.prod_processed_count[0]
    assert (c.id, c.name, c.count, c.acc_count) == (1, "cartons", 7, 7)
    assert after.stop_reason is not None and after.stop_reason.id == 42
    assert after.alarm == ()  # the alarm list is live data, the history survives
    restored = [(e.id, e.message) for e in after.alarm_history]
    assert restored[1:] == history
    assert restored[0][1].startswith("unit restarted (last saved 100.0 s before)")
    # The restored unit works and goes on counting.
    assert again.command(C.RESET).accepted
    again.em_count("em", "processed", 0, 1)
    assert again.admin().prod_processed_count[0].acc_count == 8
    again.close()


def test_shutdown_is_recorded_as_what_it_is(tmp_path: Path) -> None:
    """The unit's own shutdown (Ctrl-C, SIGTERM): an event in the alarm history, and the
    StopReason when it was producing; no alarm, no reaction; status, alarms and admin go out at
    once. In Stopped an earlier StopReason stays."""
    path = tmp_path / "u.sqlite3"
    clock = FakeClock(1_000.0)
    unit = open_unit(path, clock)
    assert unit.command(C.RESET).accepted and unit.command(C.START).accepted
    clock.advance(3.0)
    unit.drain()
    answer = unit.shutdown("SIGINT")
    assert answer.accepted and answer.message == "unit shut down (SIGINT) in EXECUTE"
    assert unit.state is S.EXECUTE and unit.alarms.alarms() == []
    assert [kind for kind, _ in unit.drain()] == ["status", "alarms", "admin"]
    unit.close()

    again = open_unit(path, clock)
    admin = again.admin()
    assert admin.stop_reason is not None
    assert (admin.stop_reason.id, admin.stop_reason.message) == (
        1000, "unit shut down (SIGINT) in EXECUTE"
    )  # fmt: skip
    assert [e.message for e in admin.alarm_history][1] == "unit shut down (SIGINT) in EXECUTE"
    assert not [e for e in admin.alarm_history if e.kind != 3]  # events only, no alarm
    # Stopped by the operator, then shut down: the operator's stop stays the StopReason.
    assert again.command(C.RESET).accepted and again.command(C.START).accepted
    assert again.command(C.STOP).accepted
    again.advance()
    again.shutdown("SIGTERM")
    assert again.stop_reason is not None and again.stop_reason.message == "STOP by operator"
    assert again.alarms.history[0].message == "unit shut down (SIGTERM) in STOPPED"
    again.close()


def test_periodic_save_without_transitions(tmp_path: Path) -> None:
    path = tmp_path / "u.sqlite3"
    clock = FakeClock()
    unit = Unit(cell_unit({"persistence": {"period": 2.0}}), clock, Store(path, "u"))
    store = unit.store
    assert store is not None
    saves = store.saves
    clock.advance(1.0)
    unit.advance()
    assert store.saves == saves
    clock.advance(1.0)
    unit.advance()
    assert store.saves == saves + 1
    doc = Store.read(path, "u")  # (the unit holds the store: read without the lock)
    assert doc is not None and doc["times"]["acc_time_since_reset"] == 2.0
    unit.close()


def test_store_keys_units_and_holds_one_at_a_time(tmp_path: Path) -> None:
    path = tmp_path / "cell.sqlite3"
    a = Store(path, "a")
    a.save({"sequence": 3}, 1.0)
    a.close()
    b = Store(path, "b")  # another unit may use the file after it (rows are keyed by unit)
    assert b.load() is None
    b.close()
    a = Store(path, "a")
    assert a.load() == {"sequence": 3, "journal": 0} and a.integrity_ok()
    a.close()
    # held by one unit at a time, and unreadable files are moved aside: test_edge_cases.py


def test_reset_counters_and_times_are_saved(tmp_path: Path) -> None:
    path = tmp_path / "u.sqlite3"
    clock = FakeClock()
    unit = open_unit(path, clock)
    unit.em_count("em", "processed", 0, 4)
    clock.advance(3.0)
    assert unit.reset_counters().accepted and unit.reset_times(all_times=True).accepted
    # No close(): what the resets journaled is what a killed process leaves.
    doc = Store.read(path, "u")
    assert doc is not None
    assert doc["counters"]["processed"][0] == [0, 4]
    assert doc["times"]["acc_time_since_reset"] == 0.0


def test_a_unit_killed_while_producing_keeps_its_time_and_says_it_crashed(tmp_path: Path) -> None:
    """Issue 24 item 5: killed in Execute (no shutdown, no snapshot), the restarted unit's
    StopReason is the crash (unplanned), not the planned remote Stop before it; and its Execute
    time is kept up to the last checkpoint (the node journals one every TIME_CHECKPOINT s).
    Killed while stopped, the stop it had stays its StopReason."""
    path = tmp_path / "u.sqlite3"
    clock = FakeClock(1_000.0)
    unit = open_unit(path, clock, persistence={"period": 60.0})
    assert unit.command(C.RESET).accepted and unit.command(C.START).accepted
    assert unit.command(C.STOP, "remote:mes").accepted
    unit.advance()
    assert unit.stop_reason is not None and unit.stop_reason.id == STOP_ID_REMOTE
    assert unit.command(C.RESET).accepted and unit.command(C.START).accepted
    assert unit.state is S.EXECUTE
    execute = Mode.PRODUCTION * 18 + S.EXECUTE
    for _ in range(7):  # 3.5 s in Execute, the node's checkpoints every 0.5 s
        clock.advance(0.5)
        unit.checkpoint(clock())
    clock.advance(0.4)  # killed 0.4 s after the last checkpoint
    assert unit.store is not None
    unit.store.close()  # SIGKILL: no shutdown, no snapshot; only the journal is left

    clock.advance(10.0)
    again = open_unit(path, clock, persistence={"period": 60.0})
    admin = again.admin()
    assert admin.stop_reason is not None and admin.stop_reason.id == STOP_ID_CRASH
    assert admin.stop_reason.message.startswith("unit process ended without shutting down")
    assert not again.stops.planned(again.mode, again.state)  # the restart is an unplanned stop
    assert again.times.state_cumulative[execute] == pytest.approx(3.5)
    assert admin.times.state_cumulative[execute] == 3

    # stopped by a remote Stop (planned), then killed: that Stop stays why it stopped
    assert again.command(C.RESET).accepted and again.command(C.START).accepted
    assert again.command(C.STOP, "remote:mes").accepted
    again.advance()
    assert again.store is not None
    again.store.close()
    third = open_unit(path, clock, persistence={"period": 60.0})
    assert third.stop_reason is not None and third.stop_reason.id == STOP_ID_REMOTE
    assert third.stops.planned(third.mode, third.state)
    third.close()


# -- the kill test --------------------------------------------------------------------------------------------
CHILD = textwrap.dedent(
    """
    import sys, time
    from packml_ros2.core import Cmd, Store, Unit, parse_cell

    path = sys.argv[1]
    doc = {"cell": "k", "units": {"u": {"persistence": False,
           "counters": {"processed": [{"id": 1, "name": "p"}], "defective": [{"id": 2}]},
           "alarms": [{"id": 7, "message": "jam", "category": 6}]}}}
    unit = Unit(parse_cell(doc).units["u"], time.time, Store(path, "u"))
    print("ready", flush=True)
    i = 0
    while True:
        i += 1
        unit.command(Cmd.RESET)
        unit.command(Cmd.START)
        unit.em_count("em", "processed", 0, 1)
        if i % 7 == 0:
            unit.em_count("em", "defective", 0, 1)
            unit.set_alarm(7, active=True)
            unit.set_alarm(7, active=False)
        if i % 50 == 0:
            unit.reset_counters()
        unit.command(Cmd.COMPLETE)
        unit.drain()
    """
)


def consistent(doc: dict[str, Any]) -> None:
    """The document read back is internally consistent."""
    times = doc["times"]
    acc = times["acc_time_since_reset"]
    assert acc >= 0
    assert sum(times["state_cumulative"].values()) == pytest.approx(acc, abs=1e-6)
    assert sum(times["mode_cumulative"].values()) == pytest.approx(acc, abs=1e-6)
    for kind, counters in doc["counters"].items():
        for count, acc_count in counters:
            assert 0 <= count <= acc_count, kind
    processed, defective = doc["counters"]["processed"][0], doc["counters"]["defective"][0]
    assert defective[1] <= processed[1]
    history = doc["alarms"]["history"]
    assert all({"id", "message", "time", "kind"} <= set(e) for e in history)
    times_newest_first = [e["time"] for e in history]
    assert times_newest_first == sorted(times_newest_first, reverse=True)


@pytest.mark.timeout(60)
def test_sigkill_at_random_moments_leaves_a_consistent_store(tmp_path: Path) -> None:
    script = tmp_path / "child.py"
    script.write_text(CHILD)
    path = tmp_path / "killed.sqlite3"
    rng = random.Random(os.getpid())
    last_acc, last_seq, last_events = 0, 0, 0
    progress = []
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    for _ in range(5):
        child = subprocess.Popen(
            [PYTHON, str(script), str(path)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            env=env,
        )
        assert child.stdout is not None
        line = child.stdout.readline()
        assert line == b"ready\n", child.stderr.read() if child.stderr else line
        time.sleep(rng.uniform(0.05, 0.3))
        child.send_signal(signal.SIGKILL)
        child.wait(timeout=10)
        assert child.returncode == -signal.SIGKILL

        store = Store(path, "u")
        assert store.integrity_ok()
        doc = store.load()
        store.close()
        assert doc is not None
        json.dumps(doc)  # plain data
        consistent(doc)
        acc = doc["counters"]["processed"][0][1]
        assert acc >= last_acc, "AccCount never goes back"
        assert doc["sequence"] >= last_seq, "sequence numbers never go back"
        history = doc["alarms"]["history"]
        assert len(history) <= 256
        events = len(history) + doc["alarms"]["history_dropped"]  # ever logged
        assert events >= last_events, "the history ring only grows or drops the oldest"
        progress.append(acc - last_acc)
        print(f"kill: AccCount {acc}, sequence {doc['sequence']}, history events {events}")
        last_acc, last_seq, last_events = acc, doc["sequence"], events
    assert sum(1 for p in progress if p > 0) >= 3, progress  # the children did work
    assert last_events > 5
    # A unit opened on the store afterwards starts in Stopped with the counters.
    clock = FakeClock(time.time())
    unit = Unit(cell_unit({"counters": {"processed": [{"id": 1}]}}), clock, Store(path, "u"))
    assert unit.state is S.STOPPED and transitions(unit)[0].trigger is Trigger.RESTART
    assert unit.admin().prod_processed_count[0].acc_count == last_acc
    assert unit.command(C.START).reason is Reason.COMMAND_NOT_ALLOWED
    assert unit.admin().alarm_history[0].message.startswith("unit restarted")
    unit.close()
