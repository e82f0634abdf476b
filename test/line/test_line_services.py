"""Issue 19: the coordinator's line services over ROS, as an MES client uses them, with hostile
requests, and a coordinator SIGKILLed and restarted (nothing of the line lost).

A two-unit line (every node a process): ``filler`` feeds ``packer``; a jam at the filler (alarm
202) stops it and starves the packer (episode 1), a full packer suspends the filler through the
interlock (episode 2). Then ``line/query_episodes`` with each filter, ``line/query_losses`` with
each window, refusals of requests that cannot be answered (nothing changes), ``line/reset_losses``,
and a restart of the coordinator from its store.
"""

from __future__ import annotations

import math
from typing import Any

import pytest
import yaml
from builtin_interfaces.msg import Time
from packml_interfaces.msg import CellStatus, LineEpisode, LineLosses, Result
from packml_interfaces.srv import Command, QueryEpisodes, QueryLosses
from std_srvs.srv import SetBool, Trigger

from packml_ros2 import line_msgs, qos
from packml_ros2.core import Cmd
from packml_ros2.testing.harness import servers_of, wait_server_gone
from packml_ros2.testing.processes import Processes
from test.ros.cells import UnitClient, start_em_process, start_unit_process, write_cell

pytestmark = pytest.mark.ros

FAST = {"resetting": 0.1, "starting": 0.1, "stopping": 0.1, "suspending": 0.05,
        "unsuspending": 0.05, "clearing": 0.1, "aborting": 0.05}  # fmt: skip
PARTS = ("planned_stop_ns", "unplanned_stop_ns", "blocked_ns", "starved_ns", "held_ns",
         "speed_loss_ns", "quality_loss_ns", "productive_ns")  # fmt: skip


def line_cell(tmp_path: Any) -> tuple[Any, str]:
    path, cell = write_cell(
        tmp_path,
        {
            "filler": {
                "remote_commands_enabled": True, "mach_speed": 600, "mach_design_speed": 600,
                "alarms": [{"id": 202, "message": "Infeed jam", "category": 2, "em": "feeder"}],
                "equipment_modules": {"feeder": {"sim": {
                    "durations": FAST, "cycle_time": 0.1, "counter": "processed",
                    "faults": {"jam": {"kind": "alarm", "alarm_id": 202}}}}},
            },
            "packer": {
                "remote_commands_enabled": True, "mach_speed": 600, "mach_design_speed": 600,
                "equipment_modules": {"loader": {"sim": {
                    "durations": FAST, "cycle_time": 0.1, "counter": "processed",
                    "fed_by": "filler", "buffer": 0.5, "faults": {"full": {"kind": "blocked"}}}}},
            },
        },
        coordinator={
            "start_order": ["packer", "filler"], "stop_order": ["filler", "packer"],
            "interlocks": [{"unit": "packer", "when": "blocked", "suspend": ["filler"]}],
        },
    )  # fmt: skip
    doc = yaml.safe_load(path.read_text())
    doc["line"] = {
        "order": ["filler", "packer"], "output_unit": "packer", "timezone": "UTC",
        "publish_period": 0.5,
        "shifts": {"early": {"start": "06:00", "end": "14:00"}, "late": {"start": "14:00", "end": "22:00"},
                   "night": {"start": "22:00", "end": "06:00"}},
    }  # fmt: skip
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path, cell


class LineClient:
    """The coordinator's services and line topics, seen from an MES client."""

    def __init__(self, ros: Any, cell: str) -> None:
        self.ros, self.base = ros, f"/{cell}/coordinator"
        self.status = ros.subscribe(CellStatus, f"{self.base}/status", qos.CELL_STATUS)
        self.episodes = ros.subscribe(LineEpisode, f"{self.base}/line/episodes", qos.LINE_EPISODES)  # fmt: skip
        self.losses = ros.subscribe(LineLosses, f"{self.base}/line/losses", qos.LINE_LOSSES)

    def command(self, cmd: Cmd) -> Command.Response:
        return self.ros.call(Command, f"{self.base}/command", Command.Request(command=int(cmd), source="operator"), 30)  # fmt: skip

    def query_episodes(self, **fields: Any) -> QueryEpisodes.Response:
        return self.ros.ask(QueryEpisodes, f"{self.base}/line/query_episodes", QueryEpisodes.Request(**fields), 10)  # fmt: skip

    def query_losses(self, **fields: Any) -> QueryLosses.Response:
        return self.ros.ask(QueryLosses, f"{self.base}/line/query_losses", QueryLosses.Request(**fields), 10)  # fmt: skip

    def running(self, what: str) -> None:
        self.status.wait_for(
            lambda m: {u.name: u.state_current_name for u in m.units} == {"filler": "EXECUTE", "packer": "EXECUTE"},
            20, what, max(0, len(self.status) - 1))  # fmt: skip


def adds_up(window: LineLosses) -> None:
    for scope in window.scopes:
        assert sum(getattr(scope, p) for p in PARTS) == scope.elapsed_ns > 0, (window.window, scope)
        assert scope.running_ns == scope.speed_loss_ns + scope.quality_loss_ns + scope.productive_ns
        assert sum(b.nanoseconds for b in scope.buckets if b.bucket != "running") == scope.elapsed_ns - scope.running_ns  # fmt: skip


def summary(eps: QueryEpisodes.Response) -> list[tuple[int, str, str]]:
    return [(e.id, e.root_unit, e.bucket) for e in eps.episodes]


def test_line_services_answer_filters_refuse_nonsense_and_survive_a_killed_coordinator(
    tmp_path: Any, ros: Any, processes: Processes
) -> None:
    path, cell = line_cell(tmp_path)
    for unit, em in (("filler", "feeder"), ("packer", "loader")):
        start_unit_process(processes, path, unit)
        start_em_process(processes, path, unit, em)
    coordinator = processes.module("coordinator", "packml_ros2.coordinator_node", str(path))
    filler, packer = UnitClient(ros, cell, "filler"), UnitClient(ros, cell, "packer")
    line = LineClient(ros, cell)
    for unit in (filler, packer):
        unit.ready(30)
        unit.wait_status(lambda m: "RESET" in m.commands_valid_names, 30, "its EMs online")
    line.status.wait_for(lambda m: m.all_online and len(m.units) == 2, 30, "both units online")
    ros.wait_for_service(QueryEpisodes, f"{line.base}/line/query_episodes", 30)
    # the cell's valid commands come from the units' rules, all or nothing
    line.status.wait_for(lambda m: list(m.commands_valid_names) == ["RESET", "ABORT"], 10, "RESET valid")  # fmt: skip
    for cmd in (Cmd.RESET, Cmd.START):
        answer = line.command(cmd)
        assert answer.accepted, answer.message
    line.running("the line running")
    running = line.status.last
    assert list(running.commands_valid_names) == ["STOP", "HOLD", "SUSPEND", "ABORT", "COMPLETE"], running  # fmt: skip
    assert list(running.commands_valid) == [
        Cmd.STOP,
        Cmd.HOLD,
        Cmd.SUSPEND,
        Cmd.ABORT,
        Cmd.COMPLETE,
    ]

    # -- episode 1: a jam at the filler; the packer runs dry ------------------------------------------
    # (30 s: a simulated EM resends an answer its client was not yet discovered for, under a
    # loaded CI the fault switch once took longer than the default 10 s)
    ros.call(SetBool, f"/{cell}/filler/feeder/fault/jam", SetBool.Request(data=True), 30)
    line.episodes.wait_for(lambda e: e.id == 1 and {(d.unit, d.how) for d in e.affected} == {("filler", "internal"), ("packer", "starved")},
                           20, "the packer starved in episode 1")  # fmt: skip
    # filler Stopped, packer Suspended: STOP (the filler is there already) and ABORT, not RESET
    line.status.wait_for(lambda m: list(m.commands_valid_names) == ["STOP", "ABORT"], 10, "STOP, ABORT valid")  # fmt: skip
    ros.call(SetBool, f"/{cell}/filler/feeder/fault/jam", SetBool.Request(data=False), 30)
    for name, then in (("reset", "IDLE"), ("start", "EXECUTE")):
        answer = filler.trigger(name)
        assert answer.success, answer.message
        filler.wait_state(then)
    line.episodes.wait_for(lambda e: e.id == 1 and not e.open, 20, "episode 1 closed")
    line.running("running again")
    # -- episode 2: the packer full; the coordinator suspends the filler -------------------------------
    ros.call(SetBool, f"/{cell}/packer/loader/fault/full", SetBool.Request(data=True), 30)
    filler.wait_status(lambda m: m.state_current_name == "SUSPENDED", 20, "the filler suspended")
    now_open = line.query_episodes(open_only=True)
    assert summary(now_open) == [(2, "packer", "blocked")] and now_open.episodes[0].open
    ros.call(SetBool, f"/{cell}/packer/loader/fault/full", SetBool.Request(data=False), 30)
    line.episodes.wait_for(lambda e: e.id == 2 and not e.open, 20, "episode 2 closed")

    # -- query_episodes and its filters -----------------------------------------------------------------
    every = line.query_episodes()
    assert every.accepted and every.total == 2
    assert summary(every) == [(2, "packer", "blocked"), (1, "filler", "unplanned_stop")]
    one, two = every.episodes[1], every.episodes[0]
    assert (one.reason, one.source, one.stop_reason_known, one.stop_reason.id) == (
        "alarm 202: Infeed jam", "alarm:202", True, 202)  # fmt: skip
    assert {(d.unit, d.how, d.cause_unit) for d in two.affected} == {("packer", "blocked", ""), ("filler", "propagated", "packer")}  # fmt: skip
    assert summary(line.query_episodes(unit="filler")) == [(1, "filler", "unplanned_stop")]
    assert summary(line.query_episodes(unit="packer", bucket="blocked")) == [(2, "packer", "blocked")]  # fmt: skip
    assert summary(line.query_episodes(unit="cell")) == []
    assert summary(line.query_episodes(reason="JAM")) == [(1, "filler", "unplanned_stop")]
    assert summary(line.query_episodes(open_only=True)) == []
    limited = line.query_episodes(limit=1)
    assert (summary(limited), limited.total) == ([(2, "packer", "blocked")], 2)
    after_one = Time(sec=one.end.sec, nanosec=one.end.nanosec)
    after_one.nanosec += 1
    if after_one.nanosec >= 10**9:
        after_one.sec, after_one.nanosec = after_one.sec + 1, after_one.nanosec - 10**9
    assert [e.id for e in line.query_episodes(since=after_one).episodes] == [2]
    assert [e.id for e in line.query_episodes(until=two.start).episodes] == [1]

    # -- query_losses: every window adds up; the line's losses name both causes --------------------
    for window in ("shift", "15min", "1h", "reset", "lifetime"):
        got = line.query_losses(window=window)
        assert got.accepted and len(got.windows) == 1, (window, got.message)
        adds_up(got.windows[0])
        assert [s.scope for s in got.windows[0].scopes] == ["", "filler", "packer"]
    shift = line.query_losses(window="shift").windows[0]
    assert shift.window.startswith("shift:") and shift.window.endswith(("early", "late", "night"))
    assert line.query_losses(window=shift.window).windows[0].window == shift.window
    reasons = {(b.bucket, b.reason) for b in shift.scopes[0].buckets}
    assert {("unplanned_stop", "filler: alarm 202: Infeed jam"), ("blocked", "packer: loader blocked")} <= reasons  # fmt: skip
    since = line.query_losses(window="since", since=one.start)
    assert since.accepted and since.windows[0].start == one.start
    adds_up(since.windows[0])
    trend = line.query_losses(window="trend", step=60.0, count=5)
    assert trend.accepted and len(trend.windows) == 5
    assert line.query_losses(window="shifts", count=3).accepted
    assert len(line.query_losses(window="trend", step=1.0, count=10**9).windows) <= 200  # bounded

    # -- refused: the reason code and a sentence; nothing changes --------------------------------------
    lifetime_before = line.query_losses(window="lifetime").windows[0].scopes[0].unplanned_stop_ns
    refusals: list[tuple[Any, str]] = [
        (line.query_losses(window="yesterday"), "yesterday"),
        (line.query_losses(window="since"), "since"),
        (line.query_losses(window="since", since=two.end, until=one.start), "after"),
        (line.query_losses(window="trend"), "step"),
        (line.query_losses(window="trend", step=math.nan), "step"),
        (line.query_losses(window="trend", step=math.inf), "step"),
        (line.query_losses(window="shift:2020-01-01 lunch"), "no shift"),
        (
            line.query_losses(window="shift:" + "x" * 100_000),
            "characters long (at most",
        ),  # the boundary
        (line.query_losses(window="\x1b[2J"), "control character U+001B"),  # the boundary
        (
            line.query_episodes(unit="nobody"),
            "no unit 'nobody' in the line (units: filler, packer; or cell)",
        ),
        (line.query_episodes(bucket="jammed"), "no bucket 'jammed'"),
        (line.query_episodes(since=two.end, until=one.start), "until must be after since"),
    ]
    for answer, why in refusals:
        assert not answer.accepted and answer.result == Result.INVALID_ARGUMENT, (why, answer.message)  # fmt: skip
        assert why in answer.message and "Traceback" not in answer.message, answer.message
        assert "\x1b" not in answer.message  # control characters come back escaped
        assert len(answer.message) < 400, answer.message  # bounded, whatever came in
    assert line.query_episodes().total == 2
    assert line.query_losses(window="lifetime").windows[0].scopes[0].unplanned_stop_ns == lifetime_before  # fmt: skip

    # -- reset_losses: the since-reset window begins now; the lifetime keeps everything ---------------
    reset = ros.call(Trigger, f"{line.base}/line/reset_losses", Trigger.Request(), 10)
    assert reset.success, reset.message
    since_reset = line.query_losses(window="reset").windows[0]
    lifetime = line.query_losses(window="lifetime").windows[0]
    assert line_msgs.ns_of(since_reset.start) > line_msgs.ns_of(two.end)
    assert since_reset.scopes[0].elapsed_ns < lifetime.scopes[0].elapsed_ns
    assert since_reset.scopes[0].unplanned_stop_ns == 0 < lifetime.scopes[0].unplanned_stop_ns

    # -- the coordinator killed at once, and started again: nothing of the line is lost ---------------
    episodes = f"{line.base}/line/query_episodes"
    assert servers_of(ros.node, episodes) == 1
    coordinator.kill()
    line.status.clear()
    line.losses.clear()
    # the dead coordinator gone from our graph first: while DDS still counts it (its participant
    # lease), our client looks ready and a query sent then can miss the new server
    wait_server_gone(ros.node, episodes)
    again = processes.module("coordinator_again", "packml_ros2.coordinator_node", str(path))
    # wait for the new one's publications (its services exist before it spins)
    try:
        line.status.wait_for(lambda m: m.all_online, 15, "the restarted coordinator's status")
    except TimeoutError:
        # once in CI the restarted coordinator ran and saw both units, and this reader heard
        # nothing in 30 s. A new reader is matched afresh; if it hears nothing either, say
        # what this process's graph holds (discovery or matching) and the coordinator's log
        line.status = ros.subscribe(CellStatus, f"{line.base}/status", qos.CELL_STATUS)
        try:
            line.status.wait_for(lambda m: m.all_online, 15, "the restarted coordinator's status")
        except TimeoutError as exc:
            graph = sorted(f"{ns}/{n}" for n, ns in ros.node.get_node_names_and_namespaces())
            writers = ros.node.get_publishers_info_by_topic(f"{line.base}/status")
            raise AssertionError(f"{exc}; nodes seen: {graph}; status writers: {len(writers)}; "
                                 f"the coordinator's log:\n{again.output()[-2000:]}") from None  # fmt: skip
    line.losses.wait_for(lambda m: True, 10, "the restarted coordinator's losses")
    again = line.query_episodes()
    assert again.accepted and summary(again) == summary(every)
    assert [(e.start, e.end, e.reason, [d.unit for d in e.affected]) for e in again.episodes] == [
        (e.start, e.end, e.reason, [d.unit for d in e.affected]) for e in every.episodes]  # fmt: skip
    restored = line.query_losses(window="lifetime").windows[0].scopes[0]
    assert restored.unplanned_stop_ns >= lifetime.scopes[0].unplanned_stop_ns
    assert restored.blocked_ns == lifetime.scopes[0].blocked_ns  # no new stop meanwhile
    assert line.query_losses(window="reset").windows[0].start == since_reset.start
    # the line runs on: a new episode continues the numbering
    ros.call(SetBool, f"/{cell}/packer/loader/fault/full", SetBool.Request(data=True), 30)
    three = line.episodes.wait_for(lambda e: e.id == 3, 20, "episode 3 after the restart")
    assert (three.root_unit, three.bucket) == ("packer", "blocked"), three
    ros.call(SetBool, f"/{cell}/packer/loader/fault/full", SetBool.Request(data=False), 30)
    line.episodes.wait_for(lambda e: e.id == 3 and not e.open, 20, "episode 3 closed")
