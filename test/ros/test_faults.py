"""Issue 4, faults: units and EMs as separate OS processes, killed for real."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from packml_interfaces.msg import Admin, EmReport, Result, Status, TransitionEvent
from packml_interfaces.srv import SetEmActive, SetMode

from packml_ros2 import qos
from packml_ros2.core import Cmd, State
from packml_ros2.testing.processes import NodeProcess, wait_until
from test.ros.cells import UnitClient, start_em_process, start_unit_process, write_cell

FAST = {"durations": {"resetting": 0.05, "starting": 0.05, "completing": 0.05, "stopping": 0.05,
                      "aborting": 0.05, "clearing": 0.05, "holding": 0.05, "unholding": 0.05}}  # fmt: skip


def _em(extra: dict | None = None, **sim) -> dict:
    return {"sim": {**FAST, "lease": 1.0, **sim, **(extra or {})}}


def _online(status: Status, *names: str) -> bool:
    ems = {e.name: e for e in status.equipment_modules}
    return all(n in ems and ems[n].online for n in names)


def test_full_production_cycles_with_three_em_processes(ros, processes, tmp_path: Path) -> None:
    ems = {
        "infeed": _em(cycle_time=0.05, counter="consumed", cycles_per_run=6),
        "robot": _em(cycle_time=0.08, counter="processed", defect_rate=0.3, cycles_per_run=4),
        "outfeed": _em(cycle_time=0.05, counter="none", cycles_per_run=5),
    }
    cell_file, cell = write_cell(
        tmp_path,
        {
            "line": {
                "equipment_modules": ems,
                "counters": {"processed": [{"id": 1, "name": "good"}]},
            }
        },
    )
    unit = start_unit_process(processes, cell_file, "line")
    for name in ems:
        start_em_process(processes, cell_file, "line", name)
    client = UnitClient(ros, cell, "line")
    client.ready()
    client.wait_status(lambda s: _online(s, *ems), 15, "three EMs online")

    for cycle in range(2):
        assert client.trigger("reset").success
        client.wait_state("IDLE")
        assert client.trigger("start").success
        client.wait_entered("EXECUTE")  # for about 0.3 s: waited for as a transition
        # Execute completes when every EM finished its run; then Completing -> Complete (waited
        # for as a transition: the status of it can arrive before the transitions before it)
        client.wait_entered("COMPLETE", timeout=10)
        runs = cycle + 1
        # (an admin message can show the robot's 4 before the infeed's 6th: both are waited for)
        client.admin.wait_for(
            lambda a, runs=runs: (
                a.prod_processed_count[0].count >= 4 * runs
                and a.prod_consumed_count[0].count >= 6 * runs
            ),
            5,
            "processed and consumed counts",
        )
    seen = [
        (t.from_state_name, t.to_state_name)
        for t in client.transitions.messages
        if t.from_state != t.to_state
    ]
    one_cycle = [("COMPLETE", "RESETTING"), ("RESETTING", "IDLE"), ("IDLE", "STARTING"), ("STARTING", "EXECUTE"),
                 ("EXECUTE", "COMPLETING"), ("COMPLETING", "COMPLETE")]  # fmt: skip
    assert seen[-6:] == one_cycle
    # every acting state waited for all three EMs: State Complete carried the sequence of its state
    for t in client.transitions.messages:
        if t.trigger == TransitionEvent.TRIGGER_STATE_COMPLETE and t.from_state == State.STARTING:
            assert t.source == "unit"
    assert unit.stop() == 0, unit.output()


def _gripper_and_robot_started(
    ros, processes, tmp_path: Path, ems: dict, lease: float, *unit_args: str
) -> tuple[UnitClient, NodeProcess]:
    """Unit ``cell_unit`` with EM processes gripper and robot, reset and sent Start; returns its
    client and the gripper's process."""
    cell_file, cell = write_cell(
        tmp_path, {"cell_unit": {"equipment_modules": ems, "em_lease": lease}}
    )
    start_unit_process(processes, cell_file, "cell_unit", *unit_args)
    gripper = start_em_process(processes, cell_file, "cell_unit", "gripper")
    start_em_process(processes, cell_file, "cell_unit", "robot")
    client = UnitClient(ros, cell, "cell_unit")
    client.ready()
    client.wait_status(lambda s: _online(s, "gripper", "robot"), 15, "EMs online")
    client.trigger("reset")
    client.wait_state("IDLE")
    client.trigger("start")
    return client, gripper


@pytest.mark.parametrize("state", ["STARTING", "EXECUTE", "STOPPING"])
def test_em_killed_in_an_acting_state_triggers_the_reaction(
    ros, processes, tmp_path: Path, state: str
) -> None:
    # 1 s: short enough to check "within the lease + 0.5 s", long enough that a stall of this
    # shared 2-core machine does not lose the EMs before the kill (0.5 s did, once in ~30 runs)
    lease = 1.0
    slow = {"durations": {**FAST["durations"], state.lower(): 30.0}} if state != "EXECUTE" else {}
    ems = {
        "gripper": _em(slow, cycle_time=5.0, lease=lease),
        "robot": _em(cycle_time=5.0, lease=lease),
    }
    client, gripper = _gripper_and_robot_started(ros, processes, tmp_path, ems, lease)
    if state == "STOPPING":
        client.wait_state("EXECUTE")
        client.trigger("stop")
    client.wait_state(state)
    killed_at, killed_wall = time.monotonic(), time.time()
    gripper.kill()
    lost = client.transitions.wait_for(
        lambda t: t.trigger == TransitionEvent.TRIGGER_EM_LOST, lease + 3.0, "EM lost reaction"
    )
    received = time.monotonic() - killed_at
    # The unit's reaction is when it decided (the transition's stamp, the unit's wall clock like
    # this one): the delivery of its message to this test's client is not the unit's timing.
    decided = lost.stamp.sec + lost.stamp.nanosec * 1e-9 - killed_wall
    assert decided <= lease + 0.5, f"reaction {decided:.3f} s after the kill (seen after {received:.3f} s)"  # fmt: skip
    assert lost.from_state_name == state and lost.to_state_name == "ABORTING"
    assert "gripper" in lost.detail
    # the lost EM is excused while aborting; the unit settles in Aborted and says which EM is gone
    status = client.wait_state("ABORTED")
    gone = {e.name: e for e in status.equipment_modules}["gripper"]
    assert not gone.online
    alarms = client.alarms.wait_for(lambda a: any("gripper" in x.message for x in a.alarms), 5)
    assert any(x.id == 9001 and x.em == "gripper" for x in alarms.alarms)
    # commands while the EM is missing get a clear answer: the EM-lost alarm (reaction Abort) is
    # still active, so even Clear is refused, naming the EM
    refused = client.command(Cmd.CLEAR)
    assert (
        not refused.accepted
        and refused.result == Result.ALARM_ACTIVE
        and "gripper" in refused.message
    )
    # recovery without the gripper (docs/packml.md §9): Maintenance, switch it off, Clear, Reset
    assert client.call(SetMode, "set_mode", mode_name="maintenance").accepted
    # accepted, the change waits for the online EM (robot) to confirm it: switching EMs needs it done
    client.wait_status(lambda s: s.unit_mode_current_name == "MAINTENANCE", 10, "Maintenance")
    assert client.call(SetEmActive, "set_em_active", em="gripper", active=False).accepted
    assert client.trigger("clear").success
    client.wait_state("STOPPED")
    assert client.trigger("reset").success
    client.wait_state("IDLE")


def test_unit_killed_and_restarted_keeps_its_admin_data(ros, processes, tmp_path: Path) -> None:
    # The EM outlives the killed unit. Until DDS drops the dead participant (its 5 s lease in
    # config/fastdds_localhost.xml), the EM's reports can stall towards the restarted unit (seen:
    # 2 s without one, while this test process received them every 0.5 s), so the EM's lease
    # must be longer than that, or the restarted unit loses it and aborts (1 run in ~10 loaded).
    lease = 6.0
    ems = {"robot": _em(cycle_time=0.05, counter="processed", defect_rate=0.2, lease=lease)}
    cell_file, cell = write_cell(tmp_path, {"packer": {"equipment_modules": ems, "em_lease": lease,
                                                        "persistence": {"path": str(tmp_path / "packer.sqlite3"), "period": 0.5}}})  # fmt: skip
    unit = start_unit_process(processes, cell_file, "packer")
    start_em_process(processes, cell_file, "packer", "robot")
    client = UnitClient(ros, cell, "packer")
    client.ready()
    client.wait_status(lambda s: _online(s, "robot"), 15, "robot online")
    client.trigger("reset")
    client.wait_state("IDLE")
    client.trigger("start")
    client.wait_state("EXECUTE")
    client.admin.wait_for(lambda a: a.prod_processed_count[0].count >= 10, 10, "10 processed")
    client.trigger("stop")
    before_status = client.wait_state("STOPPED")
    # the unit saved at the transition to Stopped: take the admin data published after it
    before = client.admin.wait_for(
        lambda a: (
            a.stamp.sec * 10**9 + a.stamp.nanosec
            >= before_status.stamp.sec * 10**9 + before_status.stamp.nanosec
        ),
        5,
    )
    unit.kill()
    client.forget()
    start_unit_process(processes, cell_file, "packer")
    after_status = client.wait_status(
        lambda s: s.sequence > before_status.sequence, 15, "restarted unit"
    )
    assert after_status.state_current == State.STOPPED
    restart = client.transitions.wait_for(lambda t: t.trigger == TransitionEvent.TRIGGER_RESTART, 5)
    assert restart.detail == "unit restarted" and restart.sequence > before_status.sequence
    after: Admin = client.admin.wait_for(lambda a: True, 5)
    assert [c.count for c in after.prod_processed_count] == [
        c.count for c in before.prod_processed_count
    ]
    assert [c.acc_count for c in after.prod_defective_count] == [
        c.acc_count for c in before.prod_defective_count
    ]
    assert (
        after.stop_reason == before.stop_reason and after.stop_reason.id == 33
    )  # STOP by operator
    assert any("unit restarted" in a.message for a in after.alarm_history)
    old = [(a.id, a.message, a.stamp) for a in before.alarm_history]
    assert (
        [(a.id, a.message, a.stamp) for a in after.alarm_history[-len(old) :]] == old
        if old
        else True
    )
    # cumulative times of states the unit is not in are identical (whole seconds)
    for index, value in enumerate(before.state_cumulative_time):
        if index % 18 != State.STOPPED:
            assert after.state_cumulative_time[index] == value, index
    # the EM re-joins the restarted unit
    client.wait_status(lambda s: _online(s, "robot"), 10, "robot re-joined")
    assert client.trigger("reset").success


def test_stale_state_complete_from_an_earlier_transition_is_ignored(
    ros, processes, tmp_path: Path
) -> None:
    ems = {"gripper": {"sim": {}}}
    cell_file, cell = write_cell(tmp_path, {"u": {"equipment_modules": ems, "em_lease": 5.0}})
    start_unit_process(processes, cell_file, "u")
    client = UnitClient(ros, cell, "u")
    client.ready()
    pub = ros.node.create_publisher(EmReport, f"/{cell}/u/em_reports", 100)
    pub.publish(EmReport(em="gripper", kind=EmReport.KIND_HEARTBEAT, lease=5.0))
    client.wait_status(lambda s: _online(s, "gripper"), 10)
    client.command(Cmd.RESET)
    resetting = client.wait_state("RESETTING")
    pub.publish(
        EmReport(
            em="gripper",
            kind=EmReport.KIND_STATE_COMPLETE,
            state=State.RESETTING,
            sequence=resetting.sequence - 1,
        )
    )
    stale = client.wait_status(
        lambda s: s.equipment_modules[0].stale_reports == 1, 5, "stale report counted"
    )
    assert stale.state_current == State.RESETTING
    pub.publish(
        EmReport(
            em="gripper",
            kind=EmReport.KIND_STATE_COMPLETE,
            state=State.RESETTING,
            sequence=resetting.sequence,
        )
    )
    client.wait_state("IDLE")


def test_a_second_unit_of_the_same_name_does_not_share_its_store(
    ros, processes, tmp_path: Path
) -> None:
    """Issue 14: the store is locked; the second unit says which process holds it and exits."""
    cell_file, cell = write_cell(tmp_path, {"u": {}})
    first = start_unit_process(processes, cell_file, "u")
    UnitClient(ros, cell, "u").ready()
    second = start_unit_process(processes, cell_file, "u")
    assert second.popen.wait(30) == 2, second.output()
    assert f"is in use by process {first.pid}" in second.output(), second.output()
    assert "Traceback" not in second.output()
    assert first.running()


def test_an_em_that_leaves_in_order_is_lost_after_the_grace(ros, processes, tmp_path: Path) -> None:
    """An EM stopped with Ctrl-C says goodbye; the unit, still running, applies the lost-EM
    reaction once ``em_leave_grace`` has passed (had the unit shut down meanwhile, as when a
    whole cell is stopped, nothing would be recorded: test_launcher_cli)."""
    grace = 1.5  # longer than an EM process takes to stop, shorter than its lease
    ems = {"gripper": _em(cycle_time=5.0, lease=5.0), "robot": _em(cycle_time=5.0, lease=5.0)}
    client, gripper = _gripper_and_robot_started(
        ros, processes, tmp_path, ems, 5.0, "-p", f"em_leave_grace:={grace}"
    )
    client.wait_state("EXECUTE")
    stopped_at = time.monotonic()
    assert gripper.stop() == 0, gripper.output()
    assert "EM gripper left unit cell_unit (SIGINT)" in gripper.output()
    lost = client.transitions.wait_for(
        lambda t: t.trigger == TransitionEvent.TRIGGER_EM_LOST, 5.0, "EM lost reaction"
    )
    waited = time.monotonic() - stopped_at
    assert grace <= waited < 5.0, f"reaction after {waited:.3f} s"  # the grace, not the lease
    assert lost.to_state_name == "ABORTING" and "gripper lost (left)" in lost.detail


def test_ems_composed_in_one_process_work_together_and_are_lost_together(
    ros, processes, tmp_path: Path
) -> None:
    """Several EMs in one process on one executor (``em_node <cell> <unit> <em> <em> ...``, as an
    integrator runs the EMs of one controller): each registers, works and reports on its own;
    the process killed, every one of them is lost within its lease."""
    ems = {name: _em(cycle_time=0.02, counter="none", cycles_per_run=3)
           for name in ("arm", "gripper", "camera")}  # fmt: skip
    cell_file, cell = write_cell(tmp_path, {"station": {"equipment_modules": ems}})
    start_unit_process(processes, cell_file, "station")
    composed = processes.module(
        "ems_station", "packml_ros2.sim_em", str(cell_file), "station", *ems
    )
    client = UnitClient(ros, cell, "station")
    client.ready()
    client.wait_status(lambda s: _online(s, *ems), 15, "three EMs of one process online")
    assert client.trigger("reset").success
    client.wait_state("IDLE")
    assert client.trigger("start").success
    client.wait_entered("COMPLETE", timeout=10)  # Execute ended when all three finished their run
    composed.kill()
    status = client.wait_status(
        lambda s: not any(e.online for e in s.equipment_modules), 5, "every EM lost"
    )
    assert status.state_current_name == "ABORTED"


def test_a_flaky_link_repeats_state_complete_and_the_unit_ignores_the_repeat(
    ros, processes, tmp_path: Path
) -> None:
    """The simulator's ``repeat_complete`` fault (sim_em.REPEAT_AFTER): every State Complete of
    the EM arrives a second time, after the unit has moved on; the unit counts it as stale and
    stays where it is."""
    from std_srvs.srv import SetBool

    from packml_ros2.sim_em import REPEAT_AFTER

    ems = {"gripper": _em(faults={"flaky": {"kind": "repeat_complete"}}, lease=5.0)}
    cell_file, cell = write_cell(tmp_path, {"u": {"equipment_modules": ems}})
    start_unit_process(processes, cell_file, "u")
    start_em_process(processes, cell_file, "u", "gripper")
    client = UnitClient(ros, cell, "u")
    client.ready()
    client.wait_status(lambda s: _online(s, "gripper"), 15, "gripper online")
    fault = f"/{cell}/u/gripper/fault/flaky"
    assert ros.call(SetBool, fault, SetBool.Request(data=True)).success

    assert client.trigger("reset").success
    idle = client.wait_state("IDLE")
    stale = client.wait_status(lambda s: s.equipment_modules[0].stale_reports == 1,
                               REPEAT_AFTER + 5, "the repeated State Complete counted stale")  # fmt: skip
    assert stale.state_current == State.IDLE and stale.sequence == idle.sequence

    off = ros.call(SetBool, fault, SetBool.Request(data=False))
    assert off.success and off.message == "flaky off (repeat_complete)", off.message


def test_ems_whose_unit_is_killed_go_to_their_safe_state_and_rejoin(ros, processes, tmp_path: Path) -> None:  # fmt: skip
    """Issue 25 item 3: the unit SIGKILLed in Execute; its EM (another process) stops producing
    within the DDS participant lease (its unit's status writer leaves the graph), runs its
    Aborting hook, says so, and follows the unit again when it is restarted."""
    ems = {"robot": _em(cycle_time=0.05, counter="processed")}
    cell_file, cell = write_cell(tmp_path, {"packer": {"equipment_modules": ems}})
    unit = start_unit_process(processes, cell_file, "packer")
    em = start_em_process(processes, cell_file, "packer", "robot")
    client = UnitClient(ros, cell, "packer")
    client.ready()
    reports = ros.subscribe(EmReport, f"/{cell}/packer/em_reports", qos.EM_REPORTS)
    client.wait_status(lambda s: _online(s, "robot"), 15, "robot online")
    client.trigger("reset")
    client.wait_state("IDLE")
    client.trigger("start")
    client.wait_state("EXECUTE")
    reports.wait_for(lambda r: r.kind == EmReport.KIND_COUNT, 5, "production")
    unit.kill()
    wait_until(lambda: "lost (its status writer left)" in em.output(), 15, what="the EM noticing")
    assert "running its ABORTING hook" in em.output()
    counted = sum(r.kind == EmReport.KIND_COUNT for r in reports.messages)
    # what was on its way when the EM noticed arrives; then nothing more for a while
    deadline = time.monotonic() + 1.5
    while time.monotonic() < deadline:
        time.sleep(0.05)
    later = sum(r.kind == EmReport.KIND_COUNT for r in reports.messages) - counted
    assert later <= 1, f"{later} counts after the EM lost its unit"
    assert em.running()

    client.forget()
    start_unit_process(processes, cell_file, "packer")
    client.ready()
    client.wait_status(lambda s: _online(s, "robot"), 15, "robot re-joined")
    wait_until(lambda: "is back: following it again" in em.output(), 15, what="the EM following")
    assert client.trigger("reset").success
    client.wait_state("IDLE")
