"""The cell coordinator over real DDS: cell commands sequenced across real unit nodes in the
configured orders, refusals naming the unit, ABORT to every unit at once, mode fan-out, the
aggregate cell state, line-interlock propagation from a simulated EM's fault, and a unit process
killed and restarted.

Units run in-process (``UnitNode`` on the harness's Context) or as processes where they are
killed; every wait is on a condition, never a fixed sleep."""

from __future__ import annotations

import itertools
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from packml_interfaces.msg import CellStatus, Result, TransitionEvent
from packml_interfaces.srv import Command, SetMode
from rclpy.node import Node
from std_srvs.srv import SetBool, Trigger

from packml_ros2 import qos
from packml_ros2.client import UnitProxy
from packml_ros2.coordinator_node import SEVERITY, CoordinatorNode, aggregate_state
from packml_ros2.core import Cmd, State, load_cell
from packml_ros2.sim_em import SimulatedEm, parse_sim
from packml_ros2.testing.harness import Collector
from packml_ros2.testing.processes import wait_until
from packml_ros2.unit_node import UnitNode
from test.ros.cells import UnitClient, start_unit_process, write_cell

pytestmark = pytest.mark.ros

#: Acting states take this long (no EMs: the minimum dwell decides), so a coordinator that did not
#: wait for each unit would command the next one while the previous is still moving.
DWELL = {"resetting": 0.15, "starting": 0.15, "stopping": 0.15, "clearing": 0.1, "aborting": 0.3}


def _unit(**extra: Any) -> dict[str, Any]:
    return {"remote_commands_enabled": True, "min_dwell": dict(DWELL), **extra}


def _ns(stamp: Any) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


class Cell:
    """A cell started in-process: its units, the coordinator and the test's view of both."""

    def __init__(self, ros: Any, tmp_path: Path, units: dict[str, Any], coordinator: dict[str, Any]) -> None:  # fmt: skip
        cell_file, self.name = write_cell(tmp_path, units, coordinator)
        self.ros = ros
        self.config = load_cell(cell_file)
        for unit in self.config.units.values():
            ros.add(UnitNode(unit, context=ros.context))
        self.coordinator = ros.add(CoordinatorNode(self.config, context=ros.context))
        self.units = {n: UnitClient(ros, self.name, n) for n in self.config.units}
        self.status: Collector[CellStatus] = ros.subscribe(
            CellStatus, f"/{self.name}/coordinator/status", qos.CELL_STATUS
        )
        for client in self.units.values():
            client.ready()
            # its latched start-up transition too: marks() count from there
            client.transitions.wait_for(lambda t: True, 10, "the latched transition")
        self.status.wait_for(lambda m: m.all_online, 10, "every unit online at the coordinator")
        ros.wait_for_service(Trigger, f"/{self.name}/coordinator/reset")

    def trigger(self, name: str, timeout: float = 20.0) -> Trigger.Response:
        return self.ros.call(Trigger, f"/{self.name}/coordinator/{name}", timeout=timeout)

    def command(self, cmd: Cmd, timeout: float = 20.0) -> Command.Response:
        return self.ros.call(Command, f"/{self.name}/coordinator/command",
                             Command.Request(command=int(cmd), source="operator:test"), timeout)  # fmt: skip

    def marks(self) -> dict[str, int]:
        return {n: len(c.transitions) for n, c in self.units.items()}

    def reached(self, unit: str, state: str, since: dict[str, int], timeout: float = 5.0) -> TransitionEvent:  # fmt: skip
        """The unit's transition into ``state`` after the mark ``since``."""
        return self.units[unit].transitions.wait_for(
            lambda t: t.to_state_name == state, timeout, f"{unit} -> {state}", since[unit]
        )

    def assert_order(self, order: list[str], acting: str, final: str, since: dict[str, int]) -> None:  # fmt: skip
        """Each unit entered ``acting`` only after the previous one had reached ``final``."""
        for previous, following in itertools.pairwise(order):
            done = self.reached(previous, final, since)
            began = self.reached(following, acting, since)
            assert _ns(began.stamp) >= _ns(done.stamp), (
                f"{following} entered {acting} before {previous} reached {final}"
            )
        for unit in order:
            assert self.reached(unit, acting, since).source == "remote:coordinator"

    def wait(self, predicate: Any, what: str, timeout: float = 10.0) -> CellStatus:
        return self.status.wait_for(predicate, timeout, what)

    def summary(self, msg: CellStatus, unit: str) -> Any:
        return next(u for u in msg.units if u.name == unit)


def test_aggregate_state_order() -> None:
    assert aggregate_state([]) == State.UNDEFINED
    assert aggregate_state([State.EXECUTE] * 3) == State.EXECUTE
    assert aggregate_state([State.EXECUTE, State.ABORTED, State.STOPPING]) == State.ABORTED
    assert aggregate_state([State.HELD, State.STOPPED, State.SUSPENDED]) == State.STOPPED
    assert aggregate_state([State.EXECUTE, State.SUSPENDED, State.HOLDING]) == State.HOLDING
    assert aggregate_state([State.EXECUTE, State.SUSPENDED]) == State.SUSPENDED
    assert aggregate_state([State.EXECUTE, State.IDLE]) == State.IDLE
    assert aggregate_state([State.EXECUTE, State.STARTING]) == State.STARTING
    assert set(SEVERITY) == set(State) - {State.UNDEFINED}


def test_cell_commands_follow_start_and_stop_order(ros, tmp_path: Path) -> None:
    start_order, stop_order = ["capper", "filler", "infeed"], ["infeed", "filler", "capper"]
    cell = Cell(ros, tmp_path, {n: _unit() for n in ("infeed", "filler", "capper")},
                {"start_order": start_order, "stop_order": stop_order, "step_timeout": 5.0})  # fmt: skip
    first = cell.wait(lambda m: m.all_online, "online")
    assert [u.name for u in first.units] == ["infeed", "filler", "capper"]
    assert first.state_current_name == "STOPPED" and first.unit_mode_current == 1
    assert all(u.health == "ok" and u.remote_commands_enabled for u in first.units)

    since = cell.marks()
    answer = cell.trigger("reset")
    assert answer.success, answer.message
    assert "capper > filler > infeed" in answer.message
    cell.assert_order(start_order, "RESETTING", "IDLE", since)

    since, seen = cell.marks(), len(cell.status)
    answer = cell.trigger("start")
    assert answer.success, answer.message
    cell.assert_order(start_order, "STARTING", "EXECUTE", since)
    # while the sequence ran, the cell said so, and was not in Execute before every unit was
    during = cell.status.messages[seen:]
    assert any(m.busy and m.sequence_step.startswith("START") for m in during)
    mixed = [m for m in during if len({u.state_current for u in m.units}) > 1]
    assert mixed and all(m.state_current_name != "EXECUTE" for m in mixed)
    running = cell.wait(
        lambda m: m.state_current_name == "EXECUTE" and not m.busy, "cell in Execute"
    )
    assert {u.state_current_name for u in running.units} == {"EXECUTE"}

    # a unit already in the target state is skipped, and the answer says so
    since = cell.marks()
    answer = cell.trigger("start")
    assert answer.success and "skipped" in answer.message and "already EXECUTE" in answer.message
    assert cell.marks() == since

    since = cell.marks()
    answer = cell.trigger("stop")
    assert answer.success, answer.message
    cell.assert_order(stop_order, "STOPPING", "STOPPED", since)
    cell.wait(lambda m: m.state_current_name == "STOPPED" and not m.busy, "cell stopped")

    # set_mode goes to every unit; the answer lists each unit's result
    answer = ros.call(SetMode, f"/{cell.name}/coordinator/set_mode",
                      SetMode.Request(mode_name="maintenance", source="remote:test"), 10)  # fmt: skip
    assert answer.accepted and answer.mode_current == 2, answer.message
    assert all(f"{u}: accepted" in answer.message for u in start_order)
    cell.wait(lambda m: m.unit_mode_current == 2, "cell in Maintenance")
    for client in cell.units.values():
        client.wait_status(lambda s: s.unit_mode_current_name == "MAINTENANCE", 5)


def test_a_cell_command_checks_every_unit_first_and_names_the_one_that_refuses(ros, tmp_path: Path) -> None:  # fmt: skip
    """Issue 14: all or nothing. A unit that cannot take the command (remote commands disabled)
    refuses it for the cell before any unit is commanded; STOP still stops every unit that can."""
    units = {"a": _unit(), "b": _unit(remote_commands_enabled=False), "c": _unit()}
    cell = Cell(ros, tmp_path, units, {"start_order": ["a", "b", "c"]})
    since = cell.marks()
    answer = cell.command(Cmd.RESET)
    assert not answer.accepted
    assert answer.result == Result.REMOTE_DISABLED and answer.state_current == State.STOPPED
    assert answer.message.startswith("RESET refused, no unit commanded: b does not take remote commands")  # fmt: skip
    assert "a " not in answer.message.split(":", 1)[1] and "c " not in answer.message.split(":", 1)[1]  # fmt: skip
    cell.wait(lambda m: [u.state_current_name for u in m.units] == ["STOPPED"] * 3, "Stopped")
    assert cell.marks() == since, "a unit was commanded"

    # a unit in a state where the command is not valid: named, with what it could do
    assert cell.units["a"].command(Cmd.RESET).accepted  # a alone (operator): Idle
    cell.units["a"].wait_state("IDLE")
    # the coordinator judges by the status it has: wait until it has seen a in Idle too
    cell.wait(
        lambda m: cell.summary(m, "a").state_current_name == "IDLE", "a in Idle at the coordinator"
    )
    since = cell.marks()
    answer = cell.command(Cmd.CLEAR)  # b and c are where CLEAR leads (Stopped): not in the way
    assert not answer.accepted and answer.result == Result.COMMAND_NOT_ALLOWED
    assert answer.message == (
        "CLEAR refused, no unit commanded: a cannot take CLEAR in IDLE (valid now: START, STOP, ABORT)"
    )
    assert cell.marks() == since

    # the mode: all or nothing too, and mode_current is the mode the cell still has
    answer = ros.call(SetMode, f"/{cell.name}/coordinator/set_mode",
                      SetMode.Request(mode=2, source="operator:test"), 10)  # fmt: skip
    assert not answer.accepted and answer.result == Result.REMOTE_DISABLED
    assert answer.mode_current == 1, answer
    assert answer.message.startswith("mode 2 refused, no unit changed: b does not take remote")
    cell.wait(lambda m: [u.unit_mode_current for u in m.units] == [1, 1, 1], "all in Production")
    assert all(t.trigger != TransitionEvent.TRIGGER_MODE
               for c in cell.units.values() for t in c.transitions.messages)  # fmt: skip


def test_a_cell_mode_change_one_unit_cannot_make_changes_no_unit(ros, tmp_path: Path) -> None:
    """Issue 14: b is in Execute, where Production allows no mode change: the cell's change to
    Maintenance is refused naming b, and a and c stay in Production (they were switched before)."""
    cell = Cell(ros, tmp_path, {n: _unit() for n in "abc"}, {"start_order": ["a", "b", "c"]})
    b = cell.units["b"]
    assert b.command(Cmd.RESET).accepted
    b.wait_state("IDLE")
    assert b.command(Cmd.START).accepted
    b.wait_state("EXECUTE")
    cell.wait(lambda m: cell.summary(m, "b").state_current_name == "EXECUTE", "b in Execute")
    answer = ros.call(SetMode, f"/{cell.name}/coordinator/set_mode",
                      SetMode.Request(mode_name="maintenance", source="remote:test"), 10)  # fmt: skip
    assert not answer.accepted and answer.result == Result.MODE_CHANGE_NOT_ALLOWED, answer
    assert "b in EXECUTE: PRODUCTION allows mode changes only in" in answer.message
    assert answer.mode_current == 1
    cell.wait(lambda m: not m.busy and [u.unit_mode_current for u in m.units] == [1, 1, 1], "done")
    for name in "ac":
        assert all(t.trigger != TransitionEvent.TRIGGER_MODE
                   for t in cell.units[name].transitions.messages)  # fmt: skip


def test_a_unit_that_refuses_the_mode_after_the_check_has_the_others_changed_back(ros, tmp_path: Path) -> None:  # fmt: skip
    """Issue 14: the check judges a unit by the cell file the coordinator has; b runs with another
    (Maintenance not allowed in Stopped) and refuses the change anyway: the units changed before
    it are changed back, and the answer says so."""
    units = {"a": _unit(), "b": _unit()}
    cell_file, name = write_cell(tmp_path, units, {"start_order": ["a", "b"]})
    config = load_cell(cell_file)
    drift = {**units, "b": _unit(modes={"maintenance": {"mode_change_states": ["Aborted"]}})}
    other = tmp_path / "other"
    other.mkdir()
    other_file, _ = write_cell(other, drift)
    other_config = load_cell(other_file)
    ros.add(UnitNode(config.units["a"], context=ros.context))
    ros.add(UnitNode(replace(other_config.units["b"], cell=name), context=ros.context))
    ros.add(CoordinatorNode(config, context=ros.context))
    status: Collector[CellStatus] = ros.subscribe(
        CellStatus, f"/{name}/coordinator/status", qos.CELL_STATUS
    )
    status.wait_for(lambda m: m.all_online, 10, "both units online")
    a = UnitClient(ros, name, "a")
    answer = ros.call(SetMode, f"/{name}/coordinator/set_mode",
                      SetMode.Request(mode_name="maintenance", source="remote:test"), 30)  # fmt: skip
    assert not answer.accepted and answer.result == Result.MODE_CHANGE_NOT_ALLOWED, answer
    assert "not set: b refused: mode change PRODUCTION -> MAINTENANCE not allowed" in answer.message
    assert answer.message.endswith("changed back: a (back)"), answer.message
    assert answer.mode_current == 1
    a.transitions.wait_for(
        lambda t: t.trigger == TransitionEvent.TRIGGER_MODE and t.to_mode == 1, 5, "a changed back"
    )
    modes = [t.to_mode for t in a.transitions.messages if t.trigger == TransitionEvent.TRIGGER_MODE]
    assert modes == [2, 1], modes
    status.wait_for(lambda m: [u.unit_mode_current for u in m.units] == [1, 1], 5, "both back")


def test_abort_reaches_every_unit_at_once_and_cancels_a_running_start(ros, tmp_path: Path) -> None:
    slow_abort = {**DWELL, "aborting": 1.0}  # sent in sequence, the Abortings would be 1 s apart
    units = {"infeed": _unit(min_dwell=slow_abort), "filler": _unit(min_dwell=slow_abort),
             "capper": _unit(min_dwell={**slow_abort, "starting": 20.0})}  # fmt: skip
    cell = Cell(ros, tmp_path, units, {"start_order": ["capper", "filler", "infeed"],
                                       "step_timeout": 25.0})  # fmt: skip
    assert cell.trigger("reset").success
    start_answer: list[Trigger.Response] = []
    starter = threading.Thread(target=lambda: start_answer.append(cell.trigger("start", 30)))
    starter.start()
    cell.wait(lambda m: m.busy and "capper" in m.sequence_step and "EXECUTE" in m.sequence_step,
              "START waiting for the capper")  # fmt: skip
    busy = cell.trigger("reset")  # other commands wait for no sequence: refused
    assert not busy.success and busy.message.startswith("RESET refused: busy (START 1/3: capper")
    since = cell.marks()
    answer = cell.trigger("abort")
    assert answer.success, answer.message
    assert answer.message.startswith("ABORT sent to every unit at once")
    starter.join(10)
    assert start_answer and not start_answer[0].success
    assert "cancelled at capper by ABORT" in start_answer[0].message
    aborting = [cell.reached(n, "ABORTING", since) for n in units]
    for unit in units:
        cell.reached(unit, "ABORTED", since)
    stamps = [_ns(t.stamp) for t in aborting]
    # sequential, each unit would have waited for the previous one's 1 s in Aborting
    assert max(stamps) - min(stamps) < 0.8e9, [t.from_state_name for t in aborting]
    assert [t.from_state_name for t in aborting] == ["IDLE", "IDLE", "STARTING"]
    cell.wait(lambda m: m.state_current_name == "ABORTED" and not m.busy, "cell aborted")
    # clear: start order again, back to Stopped
    since = cell.marks()
    assert cell.trigger("clear").success
    cell.assert_order(["capper", "filler", "infeed"], "CLEARING", "STOPPED", since)


def test_interlock_of_one_unit_suspends_its_neighbour(ros, tmp_path: Path) -> None:
    """capper's outfeed jams (blocked) -> the coordinator suspends filler; cleared -> both run.
    The second rule closes a loop: filler's own status shows 'blocked' because of the interlock
    the coordinator set, which must not be propagated back to capper."""
    sim = {"cycle_time": 0.1, "counter": "none", "faults": {"jam": {"kind": "blocked"}}}
    units = {"filler": _unit(),
             "capper": _unit(equipment_modules={"outfeed": {"sim": sim}})}  # fmt: skip
    rules = [{"unit": "capper", "when": "blocked", "suspend": ["filler"]},
             {"unit": "filler", "when": "blocked", "suspend": ["capper"]}]  # fmt: skip
    cell = Cell(ros, tmp_path, units, {"start_order": ["capper", "filler"], "interlocks": rules})
    ros.add(SimulatedEm("outfeed", "capper", cell.name, parse_sim(sim), context=ros.context))
    cell.wait(lambda m: cell.summary(m, "capper").em_online == 1, "outfeed online")
    assert cell.trigger("reset").success
    answer = cell.trigger("start")
    assert answer.success, answer.message
    cell.wait(lambda m: m.state_current_name == "EXECUTE", "cell in Execute")

    since = cell.marks()
    jam = f"/{cell.name}/capper/outfeed/fault/jam"
    assert ros.call(SetBool, jam, SetBool.Request(data=True)).success
    status = cell.wait(
        lambda m: (
            cell.summary(m, "filler").interlock_suspended
            and cell.summary(m, "filler").state_current_name == "SUSPENDED"
        ),
        "filler suspended by the coordinator",
    )
    assert cell.summary(status, "capper").blocked
    cell.wait(lambda m: m.state_current_name == "SUSPENDED", "cell Suspended")
    suspended = cell.reached("filler", "SUSPENDING", since)
    assert suspended.trigger == TransitionEvent.TRIGGER_INTERLOCK and suspended.detail == "capper blocked"  # fmt: skip
    cell.reached("capper", "SUSPENDED", since)  # by its own EM's interlock

    since = cell.marks()
    assert ros.call(SetBool, jam, SetBool.Request(data=False)).success
    cell.reached("filler", "EXECUTE", since)
    cell.reached("capper", "EXECUTE", since)
    status = cell.wait(
        lambda m: (
            m.state_current_name == "EXECUTE"
            and not any(u.interlock_suspended or u.blocked for u in m.units)
        ),
        "both back in Execute, no interlock",
    )
    capper_suspensions = [t for t in cell.units["capper"].transitions.messages
                          if t.trigger == TransitionEvent.TRIGGER_INTERLOCK and "filler" in t.detail]  # fmt: skip
    assert not capper_suspensions, "the interlock the coordinator set was propagated back"


def test_killed_unit_is_reported_lost_and_back_online(ros, processes, tmp_path: Path) -> None:
    """b runs without persistence: restarted, its sequence numbers start again, which the
    coordinator must notice to follow its transitions."""
    lease = 1.5
    cell_file, cell = write_cell(tmp_path, {"a": {"remote_commands_enabled": True},
                                            "b": {"remote_commands_enabled": True, "persistence": False,
                                                  "min_dwell": {"resetting": 0.5}}},
                                 {"start_order": ["a", "b"], "unit_lease": lease, "step_timeout": 5.0})  # fmt: skip
    start_unit_process(processes, cell_file, "a")
    b = start_unit_process(processes, cell_file, "b")
    coordinator = processes.module("coordinator", "packml_ros2.coordinator_node", str(cell_file))
    status: Collector[CellStatus] = ros.subscribe(
        CellStatus, f"/{cell}/coordinator/status", qos.CELL_STATUS
    )

    def trigger(name: str) -> Trigger.Response:
        return ros.call(Trigger, f"/{cell}/coordinator/{name}", timeout=15)

    status.wait_for(lambda m: m.all_online, 20, "both units online")
    answer = trigger("reset")
    assert answer.success, answer.message
    before = status.wait_for(lambda m: m.state_current_name == "IDLE", 5, "cell Idle")

    killed_at, mark = time.monotonic(), len(status)
    b.kill()
    lost = status.wait_for(lambda m: "b" in m.lost_units, lease + 2.0, "b lost", mark)
    detected = time.monotonic() - killed_at
    assert detected <= lease + 1.0, f"lost after {detected:.2f} s"
    assert not lost.all_online and lost.lost_units == ["b"]
    assert [(u.name, u.online, u.health) for u in lost.units] == [("a", True, "ok"), ("b", False, "offline")]  # fmt: skip
    assert lost.state_current_name == "IDLE"  # the cell state is that of the units online

    # a cell command is checked on every unit first: the lost one refuses it for all
    answer = trigger("start")
    assert not answer.success
    assert answer.message.startswith("START refused, no unit commanded: b is offline"), (
        answer.message
    )

    mark, b_transitions = len(status), UnitClient(ros, cell, "b").transitions
    start_unit_process(processes, cell_file, "b")
    back = status.wait_for(lambda m: m.all_online and not m.lost_units, 20, "b back", mark)
    assert back.units[1].health == "ok" and back.units[1].state_current_name == "STOPPED"
    assert back.units[1].sequence < before.units[1].sequence  # started again from scratch
    answer = trigger("stop")
    assert answer.success and "b (already STOPPED)" in answer.message, answer.message
    answer = trigger("reset")
    answered_at = time.time()
    assert answer.success, answer.message
    # the answer came after b had reached Idle, not on its transitions from before the restart
    # (this test's own subscription discovers the restarted process on its own: as slow as
    # "b back" under load)
    idle = b_transitions.wait_for(lambda t: t.to_state_name == "IDLE", 20, "b Idle")
    assert _ns(idle.stamp) <= answered_at * 1e9
    status.wait_for(lambda m: m.state_current_name == "IDLE", 5, "cell Idle", mark)
    assert coordinator.running()
    assert coordinator.stop() == 0, coordinator.output()
    assert "unit b lost" in coordinator.output() and "unit b online again" in coordinator.output()


def test_concurrent_cell_stops_all_succeed_once_the_cell_stopped(ros, tmp_path: Path) -> None:
    """Issue 15 item 8: ten STOPs at once used to cancel each other (9 of 10 answered failure
    although the cell stopped); a STOP while a STOP runs joins it and says so."""
    units = {"infeed": _unit(), "filler": _unit()}
    cell = Cell(ros, tmp_path, units, {"start_order": ["filler", "infeed"]})
    assert cell.trigger("reset").success
    cell.wait(lambda m: m.state_current_name == "IDLE" and not m.busy, "cell idle")
    answers: list[Trigger.Response] = []
    threads = [threading.Thread(target=lambda: answers.append(cell.trigger("stop", 40)))
               for _ in range(10)]  # fmt: skip
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert len(answers) == 10
    failed = [a.message for a in answers if not a.success]
    assert not failed, failed
    assert sum(a.message.startswith("STOP done in order") for a in answers) >= 1
    assert all(
        a.message.startswith(("STOP done", "STOP joined the STOP in progress")) for a in answers
    )
    cell.wait(lambda m: m.state_current_name == "STOPPED" and not m.busy, "cell stopped")


def test_a_units_messages_reach_the_coordinator_in_the_order_the_unit_sent_them(ros) -> None:
    """The coordinator spins with a MultiThreadedExecutor (its services wait for sequences) and
    follows each unit through a :class:`UnitProxy`: the next message of a topic must not be taken
    by another thread while the previous one still waits for the coordinator's lock, else they
    reach the line's accounting out of order. (A CI run lost a unit's return to Execute that way:
    its following departure came first, and a stop episode of the line took a later stop as its
    own.) The coordinator's handler is stood for by one that holds a lock a little while."""
    node = ros.add(Node("order_probe", context=ros.context))
    path = f"/order_probe_{id(node)}/u"
    writer = node.create_publisher(TransitionEvent, f"{path}/transitions", qos.TRANSITIONS)
    lock, seen = threading.Lock(), Collector[int]()

    def on_change(_path: str, topic: str, msg: Any) -> None:
        with lock:  # the coordinator's lock, held while a message is accounted for
            time.sleep(0.002)  # (its work: the line's store commits under that lock)
            seen(msg.sequence)

    proxy = UnitProxy(node, path, on_change, topics=("transitions",))
    wait_until(lambda: writer.get_subscription_count() > 0, 10, what="the proxy matched")
    count = 60  # within the topic's history depth (100): none is dropped
    for sequence in range(1, count + 1):
        writer.publish(TransitionEvent(sequence=sequence))
    received = seen.wait_count(count)
    assert received == sorted(received), f"taken out of order: {received}"
    proxy.destroy()
