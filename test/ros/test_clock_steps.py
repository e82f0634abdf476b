"""Issue 25 item 6: a step of the wall clock (NTP) neither silences nor aborts a cell.

The unit and its EMs run as processes whose wall clock (CLOCK_REALTIME) is stepped by libfaketime
(Debian's ``faketime``, installed by tools/setup.sh) while their monotonic clock runs on: 60 s
back, then forward again, as a machine whose time server corrects it. The timers of every node
run on the steady clock and the EM leases on the monotonic one, so ``/diagnostics`` keeps coming
through the step back and no lease "expires" at the step forward; the unit stays in Execute with
its EMs online. The engine's own deadlines move with the step (the node gives it the step as an
input, ``clock.step``): a step forward past the Execute timeout times nothing out, and the
admin data keeps coming every ``admin_period``. Timestamps stay wall-clock: they follow the step.
A recording made across the steps replays (the input log's one stamp that goes back is the
step's).
"""

from __future__ import annotations

import glob
import signal
import subprocess
import time
from pathlib import Path

import pytest
from diagnostic_msgs.msg import DiagnosticArray
from packml_interfaces.srv import SetMachSpeed

from packml_ros2 import qos
from packml_ros2.core import load_cell
from packml_ros2.testing.processes import Processes
from packml_ros2.unit_node import CLOCK_STEP, UnitNode
from test.ros.cells import UnitClient, write_cell
from test.test_replay import PACKML, ROOT, Output, packml

FAST = {"resetting": 0.05, "starting": 0.05, "stopping": 0.05, "aborting": 0.05, "clearing": 0.05}


def libfaketime() -> str:
    found = sorted(glob.glob("/usr/lib/*/faketime/libfaketimeMT.so.1"))
    if not found:
        pytest.fail("libfaketime is missing: tools/setup.sh installs Debian's faketime for the tests")  # fmt: skip
    return found[0]


def _ems_online(status, names) -> bool:  # type: ignore[no-untyped-def]
    ems = {e.name: e for e in status.equipment_modules}
    return all(n in ems and ems[n].online for n in names)


def _kill(proc: subprocess.Popen[str]) -> None:
    if proc.poll() is None:
        proc.kill()
        proc.wait(10)


def test_a_wall_clock_step_back_and_forward_neither_silences_nor_aborts_the_cell(
    ros, processes: Processes, tmp_path: Path, request: pytest.FixtureRequest
) -> None:
    offset = tmp_path / "faketime"
    offset.write_text("+0\n")
    stepped = {"LD_PRELOAD": libfaketime(), "FAKETIME_TIMESTAMP_FILE": str(offset),
               "FAKETIME_NO_CACHE": "1", "DONT_FAKE_MONOTONIC": "1"}  # fmt: skip
    ems = ("infeed", "robot")
    em = {"sim": {"durations": FAST, "lease": 1.0}}
    unit_doc = {
        "em_lease": 1.5,
        "admin_period": 1.0,
        "timeouts": {"Execute": 60.0},  # a step of 120 s forward would time Execute out
        "equipment_modules": dict.fromkeys(ems, em),
    }
    cell_file, cell = write_cell(tmp_path, {"u": unit_doc})
    processes.module("unit", "packml_ros2.unit_node", str(cell_file), "u", env=stepped)
    for name in ems:
        processes.module(f"em_{name}", "packml_ros2.sim_em", str(cell_file), "u", name, env=stepped)
    diagnostics = ros.subscribe(DiagnosticArray, "/diagnostics", qos.DIAGNOSTICS)
    unit = UnitClient(ros, cell, "u")
    unit.ready(30)
    unit.wait_status(lambda s: _ems_online(s, ems), 30, "both EMs online")
    bag = tmp_path / "steps"
    recorder = subprocess.Popen([*PACKML, "record", f"{cell}/u", "-o", str(bag)], cwd=ROOT,
                                stderr=subprocess.PIPE, text=True)  # fmt: skip
    request.addfinalizer(lambda: _kill(recorder))  # (a failing test leaves no recorder behind)
    recording = Output(recorder)
    recording.wait_for(f"receiving /{cell}/u", 30)
    for command, state in (("reset", "IDLE"), ("start", "EXECUTE")):
        assert unit.trigger(command).success
        unit.wait_state(state, 15)
    ours = f"{cell}/u"  # (the hardware id)

    def from_unit(m: DiagnosticArray) -> bool:
        return any(s.hardware_id == ours for s in m.status)

    diagnostics.wait_for(from_unit, 10, "the unit's diagnostics")
    transitions = len(unit.transitions)

    # -- 60 s back: the diagnostics (a 1 s timer) go on ------------------------------------------------
    offset.write_text("-60\n")
    start = len(diagnostics)
    for n in range(1, 4):
        diagnostics.wait_for(from_unit, 3, f"diagnostics {n} s after the step back", start)  # fmt: skip
        start = len(diagnostics)
    # the engine's periodic admin (every 1 s) goes on too, stamped with the stepped clock
    unit.admin.wait_for(lambda m: m.stamp.sec < time.time() - 50, 5, "an admin after the step back")
    # -- and forward again (60 s at once): no lease has expired, nothing stops ----------------------
    offset.write_text("+0\n")
    for _ in range(5):  # inputs: each wakes the unit 50 ms later (its input log's batch), before
        # the EMs' next heartbeats (every 0.25 s): a lease judged on the wall clock expires there
        unit.call(SetMachSpeed, "set_mach_speed", mach_speed=50.0)
        time.sleep(0.05)
    diagnostics.wait_for(from_unit, 3, "diagnostics after the step forward", len(diagnostics))  # fmt: skip
    watched_until = time.monotonic() + 3 * 1.5  # three leases of the unit
    while time.monotonic() < watched_until:
        last = unit.status.last
        assert last.state_current_name == "EXECUTE" and _ems_online(last, ems), last
        time.sleep(0.1)
    # -- 120 s forward: Execute's 60 s timeout does not fire, the admin goes on -------------------
    offset.write_text("+120\n")
    unit.call(SetMachSpeed, "set_mach_speed", mach_speed=40.0)  # (an input: the step is seen)
    unit.admin.wait_for(lambda m: m.stamp.sec > time.time() + 100, 5, "an admin after the step forward")  # fmt: skip
    watched_until = time.monotonic() + 3.0
    while time.monotonic() < watched_until:
        assert unit.status.last.state_current_name == "EXECUTE", [
            (t.from_state_name, t.to_state_name, t.source, t.detail)
            for t in unit.transitions.messages[transitions:]
        ]
        time.sleep(0.1)
    assert [(t.from_state_name, t.to_state_name) for t in unit.transitions.messages[transitions:]] == []  # fmt: skip
    assert unit.trigger("stop").success
    unit.wait_state("STOPPED", 15)
    stop = unit.transitions.messages[-1]
    assert stop.stamp.sec > time.time() + 100, "a transition is stamped with the stepped clock"
    # -- the recording across the steps replays ----------------------------------------------------
    recorder.send_signal(signal.SIGINT)
    text = recording.rest()
    assert recorder.returncode == 0 and "Traceback" not in text, text
    replayed = packml("replay", str(bag), timeout=120)
    assert replayed.returncode == 0, replayed.stdout + replayed.stderr


def _steps(node: UnitNode) -> list[str]:
    return [e.message for e in node.unit.alarms.history if "wall clock stepped" in e.message]


def test_a_thread_held_between_the_clock_reads_is_not_a_step(ros, tmp_path: Path) -> None:
    """On a loaded host the node's thread can be held for longer than CLOCK_STEP between its
    read of the wall clock and of the monotonic one: that is no step of the clock, and the
    engine must not move its deadlines (a false step back fired them early). A real step read
    promptly is still one."""
    cell_file, _ = write_cell(tmp_path, {"u": {"equipment_modules": {}}})
    node = UnitNode(load_cell(cell_file).units["u"], context=ros.context)
    try:
        wall = node._now
        node._time()  # (the first read: the offset to compare with)

        def held() -> float:  # the wall clock read, then the thread held 0.4 s
            now = wall()
            time.sleep(2 * CLOCK_STEP - 0.1)
            return now

        node._now = held  # type: ignore[method-assign]
        node._time()
        node._now = wall  # type: ignore[method-assign]
        node._time()
        assert _steps(node) == []

        node._now = lambda: wall() + 60.0  # type: ignore[method-assign]
        node._time()
        (step,) = _steps(node)
        assert "stepped +60." in step, step
    finally:
        node.destroy_node()
