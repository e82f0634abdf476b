"""Issue 14 (b): edge cases a plant hits, engine side. Each test failed before its fix.

Node-side cases (an EM switched active mid-state, the configured lease, a stray heartbeat, two
units on one store, the coordinator) are in test/ros."""

from __future__ import annotations

import json
import os
import random
import signal
import sqlite3
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

import pytest

from packml_ros2.core import Cmd as C
from packml_ros2.core import Mode, Reason, State, Store, Unit
from packml_ros2.core.persistence import StoreLocked

from .helpers import FakeClock, cell_unit

S = State
PYTHON = sys.executable


# -- 4: ModeCurrentTime of a mode left is 0 (docs/packml.md §6) ------------------------------------
def test_mode_current_time_is_zero_after_leaving_the_mode() -> None:
    clock = FakeClock()
    unit = Unit(cell_unit({}), clock)
    clock.advance(7.0)
    assert unit.set_mode("maintenance").accepted and unit.mode == Mode.MAINTENANCE
    clock.advance(3.0)
    unit.advance()
    times = unit.admin().times
    assert times.mode_current[Mode.PRODUCTION] == 0
    assert times.mode_cumulative[Mode.PRODUCTION] == 7
    assert times.mode_current[Mode.MAINTENANCE] == 3
    assert unit.set_mode("production").accepted
    clock.advance(2.0)
    unit.advance()
    times = unit.admin().times
    assert times.mode_current[Mode.MAINTENANCE] == 0
    assert times.mode_cumulative[Mode.MAINTENANCE] == 3
    assert times.mode_current[Mode.PRODUCTION] == 2  # since it was entered again


# -- 5: counters only go up ------------------------------------------------------------------------------------
def test_negative_count_increment_is_refused() -> None:
    clock = FakeClock()
    unit = Unit(cell_unit({"counters": {"processed": [{"id": 1}]}}), clock)
    assert unit.em_count("em", "processed", 0, 5).accepted
    refused = unit.em_count("em", "processed", 0, -3)
    assert not refused.accepted and refused.reason is Reason.INVALID_ARGUMENT
    assert "-3" in refused.message
    counter = unit.admin().prod_processed_count[0]
    assert (counter.count, counter.acc_count) == (5, 5)


# -- 3: a stray report never registers an EM mid-production --------------------------------------------
def test_an_unknown_ems_report_registers_it_only_at_rest() -> None:
    unit = Unit(cell_unit({}), FakeClock())  # allow_registration: true (the default)
    assert unit.command(C.RESET).accepted and unit.command(C.START).accepted
    assert unit.state is S.EXECUTE and unit.mode == Mode.PRODUCTION
    for _ in range(3):  # its heartbeats keep coming: refused each time, said once in the log
        refused = unit.em_seen("stray", report=True)
        assert not refused.accepted and refused.reason is Reason.EM_UNKNOWN, refused
    assert "only at rest" in refused.message and "EXECUTE" in refused.message
    logs = [text for kind, (level, text) in _logs(unit)]
    assert sum("stray" in text for text in logs) == 1, logs
    assert unit.equipment.get("stray") is None and unit.state is S.EXECUTE
    assert unit.command(C.STOP).accepted and unit.state is S.STOPPED  # at rest: it registers
    assert unit.em_seen("stray", report=True).accepted
    assert unit.equipment.get("stray") is not None


# -- 6: nothing answered is lost on SIGKILL ---------------------------------------------------------------------
KILLED = textwrap.dedent(
    """
    import sys, time
    from packml_ros2.core import Store, Unit, parse_cell

    doc = {"cell": "k", "units": {"u": {"persistence": {"period": 60},
           "counters": {"processed": [{"id": 1, "name": "p"}]},
           "alarms": [{"id": 7, "message": "jam", "category": 6}]}}}
    unit = Unit(parse_cell(doc).units["u"], time.time, Store(sys.argv[1], "u"))
    out = sys.stdout
    print("ready", flush=True)
    i = 0
    while True:
        i += 1
        assert unit.em_count("em", "processed", 0, 1).accepted
        out.write(f"count {i}\\n"); out.flush()           # answered: must survive
        if i % 5 == 0:
            assert unit.set_alarm(7, active=True).accepted
            assert unit.ack_alarms().accepted
            out.write(f"ack {i}\\n"); out.flush()
            assert unit.set_alarm(7, active=False).accepted
            assert unit.reset_alarms().accepted
        unit.drain()
    """
)


@pytest.mark.timeout(90)
def test_nothing_answered_is_lost_on_sigkill(tmp_path: Path) -> None:
    """No transition happens (they used to save), only counts, alarms and acknowledgements:
    whatever the child was answered before the kill is in the store afterwards."""
    script = tmp_path / "child.py"
    script.write_text(KILLED)
    path = tmp_path / "killed.sqlite3"
    rng = random.Random(os.getpid())
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    total = 0
    for _ in range(4):
        child = subprocess.Popen([PYTHON, str(script), str(path)], stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, env=env, text=True)  # fmt: skip
        assert child.stdout is not None
        assert child.stdout.readline() == "ready\n", child.stderr.read() if child.stderr else ""
        time.sleep(rng.uniform(0.2, 0.6))
        child.send_signal(signal.SIGKILL)
        child.wait(timeout=10)
        lines = child.stdout.read().splitlines()
        counts = [int(x.split()[1]) for x in lines if x.startswith("count ")]
        acks = [x for x in lines if x.startswith("ack ")]
        assert counts, "the child counted"
        total += counts[-1]
        clock = FakeClock(time.time())
        unit = Unit(cell_unit({"counters": {"processed": [{"id": 1}]},
                               "alarms": [{"id": 7, "message": "jam", "category": 6}]}),
                    clock, Store(path, "u"))  # fmt: skip
        admin = unit.admin()
        assert admin.prod_processed_count[0].acc_count >= total, "an answered count was lost"
        total = admin.prod_processed_count[0].acc_count
        # every occurrence the child was told was acknowledged is, as far as the history ring
        # (256) reaches back: only the newest may have been killed before its acknowledgement
        jams = [e for e in admin.alarm_history if e.id == 7]  # newest first
        assert len(jams) >= min(len(acks), 200) and acks
        assert all(e.ack_time is not None for e in jams[1:]), "an acknowledgement was lost"
        unit.close()


# -- 7: a corrupt or foreign store ---------------------------------------------------------------------------------
def _garbage(path: Path) -> None:
    path.write_bytes(bytes(random.Random(7).randrange(256) for _ in range(5000)))


def _row(path: Path, schema: int, document: str) -> None:
    Store(path, "u").close()
    db = sqlite3.connect(path)
    db.execute("INSERT INTO unit_admin VALUES ('u', ?, 0.0, ?)", (schema, document))
    db.commit()
    db.close()


def _bad_json(path: Path) -> None:
    _row(path, 1, "{not json")


def _other_schema(path: Path) -> None:
    _row(path, 99, "{}")


def _wrong_types(path: Path) -> None:
    doc = {"sequence": "many", "counters": {"processed": [["a", None]]}, "times": [1, 2],
           "alarms": {"history": [{"id": "x"}]}}  # fmt: skip
    _row(path, 1, json.dumps(doc))


def _foreign(path: Path) -> None:
    db = sqlite3.connect(path)
    db.execute("CREATE TABLE photos (id INTEGER, data BLOB)")
    db.execute("INSERT INTO photos VALUES (1, x'00ff')")
    db.commit()
    db.close()


@pytest.mark.parametrize("spoil", [_garbage, _bad_json, _other_schema, _wrong_types, _foreign])
def test_unreadable_store_is_moved_aside_and_the_unit_starts_with_an_alarm(
    tmp_path: Path, spoil: Any
) -> None:
    path = tmp_path / "u.sqlite3"
    spoil(path)
    before = path.read_bytes()
    clock = FakeClock()
    unit = Unit(cell_unit({"counters": {"processed": [{"id": 1}]}}), clock, Store(path, "u"))
    assert unit.state is S.STOPPED
    logs = [text for kind, item in unit.drain() if kind == "log" for _, text in [item]]
    aside = [p for p in tmp_path.iterdir() if p.name.startswith("u.sqlite3.unreadable")]
    assert len(aside) == 1 and aside[0].read_bytes() == before, sorted(tmp_path.iterdir())
    assert any(aside[0].name in text for text in logs), logs
    alarms = unit.admin().alarm
    assert [a.id for a in alarms] == [9004], alarms
    assert aside[0].name in alarms[0].message
    # the unit works, and saves to a fresh store at the old path
    assert unit.command(C.RESET).accepted and unit.em_count("em", "processed", 0, 2).accepted
    unit.close()
    again = Unit(cell_unit({"counters": {"processed": [{"id": 1}]}}), clock, Store(path, "u"))
    assert again.admin().prod_processed_count[0].acc_count == 2
    assert not again.admin().alarm
    again.close()


def test_a_store_is_held_by_one_unit_at_a_time(tmp_path: Path) -> None:
    path = tmp_path / "u.sqlite3"
    first = Store(path, "u")
    with pytest.raises(StoreLocked, match=f"process {os.getpid()}"):
        Store(path, "u")
    first.close()
    Store(path, "u").close()  # free again once closed


def _logs(unit: Unit) -> list[tuple[str, tuple[str, str]]]:
    return [(kind, item) for kind, item in unit.drain() if kind == "log"]
