"""Issue 16: recording a running unit from any moment, for real: a unit node that has applied a
million inputs (its engine driven in-process, fast) and then thousands more over DDS (EM
reports), recorded for ten seconds by ``packml record`` while an operator and a real EM process
work it; ``packml replay`` starts from the snapshot the unit published when the recorder joined
and matches."""

from __future__ import annotations

import subprocess
import time
from pathlib import Path
from typing import Any

import pytest
from packml_interfaces.msg import EmReport

from packml_ros2 import qos
from packml_ros2.bag.recording import load
from packml_ros2.bag.replay import replay
from packml_ros2.core import Cmd, State, load_cell
from packml_ros2.unit_node import UnitNode
from test.ros.cells import UnitClient, start_em_process, write_cell
from test.test_replay import PACKML, ROOT, Output, packml

pytestmark = pytest.mark.ros

UNIT = {
    "persistence": False,  # (its journal would write each of the million inputs: 70 us each)
    "equipment_modules": {
        "feeder": {
            "sim": {"durations": {"resetting": 0.1, "starting": 0.1, "stopping": 0.1,
                                  "holding": 0.1, "unholding": 0.1},
                    "cycle_time": 0.2, "counter": "processed"},
        },
        "counter": {"active": False},  # the test's node reports as this one: its counts
    },
    "alarms": [{"id": 7, "message": "jam", "category": 2}],
}  # fmt: skip


def million_inputs(node: UnitNode) -> int:
    """A million inputs applied to the node's engine in-process: production cycles of the feeder
    (State Complete, counts), holds, a stopping alarm now and then, on the node's own clock.
    Their input log is counted but not published (publishing costs ~46 us a message: 46 s),
    nor are their outputs (the publication numbers a recorder sees start after them); nobody
    subscribes at that time, and the snapshot a recorder gets later holds their effect."""
    unit = node.unit

    def logged(t: float, name: str, args: dict[str, Any]) -> None:
        node._input_index += 1

    unit.on_input = logged
    em_complete, command, em_count = unit.em_complete, unit.command, unit.em_count
    unit.em_seen("feeder", True)
    executes = 0
    while node._input_index < 1_000_000:
        state = unit.state
        if state is State.STOPPED or state is State.COMPLETE:
            if unit.alarms.active_count():
                unit.set_alarm(7, 0, False)
                unit.reset_alarms()
            command(Cmd.RESET)
        elif state is State.IDLE:
            command(Cmd.START)
        elif state is State.HELD:
            command(Cmd.UNHOLD)
        elif state is State.EXECUTE:
            executes += 1
            if executes % 9 == 0:
                command(Cmd.HOLD)
            elif executes % 301 == 0:
                unit.set_alarm(7, 0, True)
        em_complete("feeder", int(unit.state), unit.sequence)
        em_count("feeder", "processed", 0, 1)
        unit.drain()
    command(Cmd.STOP)
    em_complete("feeder", int(unit.state), unit.sequence)
    unit.drain()
    assert unit.state is State.STOPPED, unit.state
    unit.on_input = node._on_input
    return node._input_index


def test_a_unit_that_ran_a_million_inputs_is_recorded_for_ten_seconds(
    tmp_path: Path, ros: Any, processes: Any
) -> None:
    cell_file, cell = write_cell(tmp_path, {"u": UNIT})
    config = load_cell(cell_file).units["u"]
    node = UnitNode(config, context=ros.context, source=cell_file.read_text())
    t0 = time.perf_counter()
    before = million_inputs(node)
    fast = time.perf_counter() - t0
    ros.add(node)
    unit = UnitClient(ros, cell, "u")
    unit.ready()

    # thousands more over DDS: count reports of the (inactive) EM "counter", as it publishes them
    pub = ros.node.create_publisher(EmReport, f"/{cell}/u/em_reports", qos.EM_REPORTS)

    def counts(n: int) -> None:
        for _ in range(n // 100):
            target = node._input_index + 100
            for _ in range(100):
                pub.publish(EmReport(em="counter", kind=EmReport.KIND_COUNT, increment=1,
                                     counter=EmReport.COUNTER_CONSUMED))  # fmt: skip
            deadline = time.monotonic() + 10
            while node._input_index < target and time.monotonic() < deadline:
                time.sleep(0.005)

    counts(6000)
    assert node._input_index >= before + 6000

    start_em_process(processes, cell_file, "u", "feeder")
    unit.wait_status(lambda s: any(e.name == "feeder" and e.online for e in s.equipment_modules),
                     15, "feeder online")  # fmt: skip
    bag = tmp_path / "bag"
    proc = subprocess.Popen([*PACKML, "record", f"{cell}/u", "--duration", "10", "-o", str(bag)],
                            cwd=ROOT, stderr=subprocess.PIPE, text=True)  # fmt: skip
    out = Output(proc)
    out.wait_for(f"receiving /{cell}/u")
    for name, state in (("reset", "IDLE"), ("start", "EXECUTE"), ("hold", "HELD"),
                        ("unhold", "EXECUTE")):  # fmt: skip
        assert unit.trigger(name).success
        unit.wait_state(state)
    counts(300)
    assert unit.trigger("stop").success
    unit.wait_state("STOPPED")
    text = out.rest()
    assert proc.returncode == 0 and "Traceback" not in text, text

    rec = load(bag).unit("u")
    (snap,) = rec.snapshots
    assert snap.index > 1_006_000
    assert min(i.index for i in rec.inputs) > 1_000_000  # the history: the last 5000 inputs
    out2 = packml("replay", str(bag))
    assert out2.returncode == 0, out2.stdout + out2.stderr
    assert f"from a snapshot after input #{snap.index}" in out2.stdout
    u = replay(bag).units[0]
    assert u.compared["transitions"] >= 10 and u.compared["status"] >= 10
    print(
        f"{before} inputs in-process in {fast:.1f} s; snapshot after #{snap.index}; "
        f"{len(u.inputs)} inputs replayed, {sum(u.compared.values())} outputs compared"
    )
