"""Issue 4: the EM base class integrators build on, against a real unit node over DDS."""

from __future__ import annotations

import asyncio
import threading
import time
from pathlib import Path

import pytest
from packml_interfaces.msg import Status
from packml_interfaces.srv import SetEmActive

from packml_ros2 import qos
from packml_ros2.core import Cmd, State
from packml_ros2.equipment_module import EquipmentModule, StateContext
from packml_ros2.ros import interface
from packml_ros2.testing.processes import wait_until
from packml_ros2.unit_node import UnitNode
from test.ros.cells import UnitClient, unit_config_of, write_cell


class Recorder(EquipmentModule):
    """Records what its hooks did, with times."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.events: list[tuple[str, float]] = []
        self.lock = threading.Lock()

    def note(self, what: str) -> None:
        with self.lock:
            self.events.append((what, time.monotonic()))

    def names(self) -> list[str]:
        with self.lock:
            return [e for e, _ in self.events]

    def when(self, what: str) -> float:
        with self.lock:
            return next(t for e, t in self.events if e == what)


class Robot(Recorder):
    async def on_starting(self, ctx: StateContext) -> None:  # a coroutine that takes time
        self.note("starting")
        await asyncio.sleep(0.3)
        self.note("started")

    async def execute(self, ctx: StateContext) -> None:
        while True:
            await ctx.finish(self.move())

    async def move(self) -> None:
        self.note("move begin")
        await asyncio.sleep(0.4)
        self.note("move end")
        self.count("processed")

    async def on_holding(self, ctx: StateContext) -> None:
        self.note("holding")

    def on_stopping(self, ctx: StateContext) -> None:  # a plain function, in a worker thread
        self.note("stopping")
        ctx.sleep(0.1)
        self.note("stopped")

    def on_completing(self, ctx: StateContext) -> None:  # runs until the unit leaves Completing
        self.note("completing")
        while ctx.sleep(0.02):
            pass
        self.note("completing cancelled")


@pytest.fixture
def cell(ros, tmp_path: Path):
    cell_file, cell = write_cell(
        tmp_path,
        {"u": {"equipment_modules": {"robot": {}}, "em_lease": 2.0,
               "alarms": [{"id": 500, "message": "vacuum low", "category": 6, "warning": True}]}},
    )  # fmt: skip
    unit = UnitNode(unit_config_of(cell_file, "u"), context=ros.context)
    ros.add(unit)
    client = UnitClient(ros, cell, "u")
    client.ready()
    return cell, client  # the harness destroys (and so closes) the unit after its executor stopped


def em(ros, cls: type[EquipmentModule], cell: str, name: str = "robot", **kw) -> EquipmentModule:
    node = cls(name, "u", cell, context=ros.context, **kw)
    ros.add(node)
    return node


def wait_note(node: Recorder, what: str, timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while what not in node.names():
        assert time.monotonic() < deadline, f"{what!r} never happened: {node.names()}"
        time.sleep(0.01)


def to_execute(client: UnitClient) -> None:
    """Reset and Start the unit; back once it is in Execute."""
    client.trigger("reset")
    client.wait_state("IDLE")
    client.trigger("start")
    client.wait_state("EXECUTE")


def start_unit(ros, cell_file: Path, cell_name: str) -> UnitClient:
    """Unit ``u`` of ``cell_file`` in the test's executor, and a client of it once it answers."""
    ros.add(UnitNode(unit_config_of(cell_file, "u"), context=ros.context))
    client = UnitClient(ros, cell_name, "u")
    client.ready()
    return client


def online(client: UnitClient, name: str = "robot") -> None:
    client.wait_status(
        lambda s: any(e.name == name and e.online for e in s.equipment_modules),
        10,
        f"{name} online",
    )


def test_state_complete_is_reported_when_the_hook_returns(ros, cell) -> None:
    cell_name, client = cell
    robot = em(ros, Robot, cell_name)
    online(client)
    client.trigger("reset")
    client.wait_state("IDLE")  # no on_resetting: completed at once
    client.trigger("start")
    execute = client.wait_state("EXECUTE")
    assert robot.names()[:2] == ["starting", "started"]
    # (status and transitions are two topics: the transition may come after the status)
    starting = client.transitions.wait_for(lambda t: t.to_state_name == "EXECUTE", 5, "into Execute")  # fmt: skip
    assert starting.sequence == execute.sequence
    client.admin.wait_for(lambda a: a.prod_processed_count[0].count >= 1, 5, "a counted move")


def test_hold_in_the_middle_of_a_move_finishes_the_move_then_pauses(ros, cell) -> None:
    cell_name, client = cell
    robot = em(ros, Robot, cell_name)
    online(client)
    to_execute(client)
    deadline = time.monotonic() + 5
    while (
        robot.names().count("move begin") <= robot.names().count("move end")
        and time.monotonic() < deadline
    ):
        time.sleep(0.01)  # polling the EM's own record: wait until a move is under way
    hold_at = time.monotonic()
    assert client.trigger("hold").success
    client.wait_state("HELD", timeout=5)
    held_at = time.monotonic()
    names = robot.names()
    last_begin = max(i for i, n in enumerate(names) if n == "move begin")
    assert names[last_begin:] == ["move begin", "move end", "holding"]
    assert robot.when("holding") >= hold_at and held_at >= robot.when("holding")


def test_a_plain_hook_sees_cancellation_when_the_unit_leaves_its_state(ros, cell) -> None:
    cell_name, client = cell
    robot = em(ros, Robot, cell_name)
    online(client)
    to_execute(client)
    client.trigger("complete")
    client.wait_state("COMPLETING")
    wait_note(robot, "completing")  # the running move finishes first, then on_completing starts
    assert client.trigger("stop").success  # Completing -> Stopping: the hook must give up
    client.wait_state("STOPPED", timeout=5)
    names = robot.names()
    assert names.index("completing cancelled") < names.index("stopping") < names.index("stopped")


def test_a_failing_hook_raises_the_fault_alarm(ros, cell) -> None:
    class Broken(EquipmentModule):
        async def on_starting(self, ctx: StateContext) -> None:
            raise RuntimeError("servo not ready")

    cell_name, client = cell
    em(ros, Broken, cell_name)
    online(client)
    client.trigger("reset")
    client.wait_state("IDLE")
    client.trigger("start")
    alarms = client.alarms.wait_for(lambda a: any(x.id == 9100 for x in a.alarms), 5, "fault alarm")
    fault = next(x for x in alarms.alarms if x.id == 9100)
    assert "servo not ready" in fault.message and fault.category == 2
    client.wait_state("STOPPED", timeout=5)  # category 2: Stop


def test_requests_counts_alarms_and_interlocks_reach_the_unit(ros, cell) -> None:
    class Plain(EquipmentModule):
        async def execute(self, ctx: StateContext) -> None:  # runs until the unit leaves Execute
            await asyncio.Event().wait()

    cell_name, client = cell
    node = em(ros, Plain, cell_name)
    online(client)
    to_execute(client)
    node.count("processed", 3)
    node.count("defective", 1)
    admin = client.admin.wait_for(lambda a: a.prod_processed_count[0].count == 3, 5, "counts")
    assert admin.prod_defective_count[0].count == 1
    node.raise_alarm(500, message="")  # configured warning: listed, never acts
    warnings = client.alarms.wait_for(
        lambda a: any(w.id == 500 and w.trigger for w in a.warnings), 5
    )
    assert warnings.warnings[0].message == "vacuum low"
    node.clear_alarm(500)
    client.alarms.wait_for(lambda a: any(w.id == 500 and not w.trigger for w in a.warnings), 5)
    assert client.status.last.state_current_name == "EXECUTE"
    node.set_interlock(blocked=True)
    client.wait_state("SUSPENDED")
    assert client.status.last.equipment_interlock.blocked
    node.set_interlock(blocked=False)
    client.wait_state("EXECUTE")
    node.request(Cmd.STOP)
    stopping = client.transitions.wait_for(lambda t: t.to_state_name == "STOPPING", 5)
    assert stopping.source == "em:robot"


def test_an_em_that_restarts_rejoins_at_the_current_state_and_sequence(ros, cell) -> None:
    class Slow(Recorder):
        async def on_starting(self, ctx: StateContext) -> None:
            self.note(f"starting {ctx.sequence}")
            await asyncio.sleep(60)

    class Quick(Recorder):
        async def on_starting(self, ctx: StateContext) -> None:
            self.note(f"starting {ctx.sequence}")

    cell_name, client = cell
    first = em(ros, Slow, cell_name)
    online(client)
    client.trigger("reset")
    client.wait_state("IDLE")
    client.trigger("start")
    starting = client.wait_state("STARTING")
    deadline = time.monotonic() + 5
    while not first.names() and time.monotonic() < deadline:
        time.sleep(0.01)
    # the EM process "crashes" (no goodbye) and a new instance comes up within the lease
    ros.executor.remove_node(first)
    first.destroy_node()
    second = em(ros, Quick, cell_name)
    client.wait_state("EXECUTE", timeout=5)
    assert second.names() == [f"starting {starting.sequence}"]
    assert not any(t.trigger_name == "EM_LOST" for t in client.transitions.messages)


def test_an_em_switched_active_mid_state_joins_it(ros, tmp_path: Path) -> None:
    """Issue 14: in Maintenance, an EM switched active while the unit waits in an acting state
    owes State Complete for it: it runs that state's hook and reports (it used to never report:
    the unit hung in Resetting, or in Aborting with no command left)."""
    release = threading.Event()

    class Busy(Recorder):
        def on_resetting(self, ctx: StateContext) -> None:
            self.note("resetting")
            while not release.is_set() and ctx.sleep(0.01):
                pass

    class Late(Recorder):
        async def on_resetting(self, ctx: StateContext) -> None:
            self.note(f"resetting {ctx.sequence}")

    cell_file, cell_name = write_cell(
        tmp_path,
        {"u": {"initial_mode": "maintenance", "em_lease": 2.0,
               "equipment_modules": {"busy": {}, "late": {"active": False}}}},
    )  # fmt: skip
    client = start_unit(ros, cell_file, cell_name)
    busy = em(ros, Busy, cell_name, "busy")
    late = em(ros, Late, cell_name, "late")
    online(client, "busy")
    online(client, "late")
    client.trigger("reset")
    resetting = client.wait_state("RESETTING")
    wait_note(busy, "resetting")
    assert not late.names()  # inactive: it sat this state out
    assert client.call(SetEmActive, "set_em_active", em="late", active=True).accepted
    wait_note(late, f"resetting {resetting.sequence}")
    release.set()
    client.wait_state("IDLE", timeout=5)


def test_bytes_on_the_status_topic_that_are_no_status_are_refused_and_change_nothing(
    ros, cell
) -> None:
    """An EM reads its unit's status straight from the bytes (packml_ros2.cdr_fields): what is
    not a status (a raw writer on the topic) is refused with a warning, and the EM goes on."""
    cell_name, client = cell
    robot = em(ros, Robot, cell_name)
    online(client)
    # online at the unit = its first report arrived; the unit's status reaches the EM on its own
    wait_until(lambda: robot.status is not None, 10, what="the unit's status at the EM")
    before = robot.status
    assert before is not None and robot.state.name == "STOPPED"
    writer = ros.node.create_publisher(Status, f"/{cell_name}/u/status", qos.STATUS)
    deadline = time.monotonic() + 10
    while writer.get_subscription_count() < 2:  # the robot and the test's own client
        assert time.monotonic() < deadline, "the writer never matched the EM"
        time.sleep(0.01)
    bad = (b"\x00\x01\x00\x00" + b"\xff" * 40, b"\x00\x07\x00\x00" + bytes(60), b"\x00")
    for n, raw in enumerate(bad, 1):  # one by one: the status topic keeps the last message only
        writer.publish(raw)
        deadline = time.monotonic() + 10
        while robot.refused_statuses < n:
            assert time.monotonic() < deadline, f"{raw!r} not refused"
            time.sleep(0.01)
    assert robot.status == before and robot.unit_status is not None
    assert robot.unit_status.state_current_name == "STOPPED"
    ros.node.destroy_publisher(writer)
    to_execute(client)
    assert robot.names()[:2] == ["starting", "started"]


class Resetter(Recorder):
    def on_resetting(self, ctx: StateContext) -> None:
        self.note(f"resetting {ctx.sequence}")


def test_a_status_from_a_second_writer_does_not_drive_the_em(ros, cell) -> None:
    """Issue 25 item 7: an EM binds its unit's status writer as the unit binds its EMs'
    writers: a forged Status (a state the unit never entered) from another writer runs no hook."""
    cell_name, client = cell
    robot = em(ros, Resetter, cell_name)
    online(client)
    # the EM binds the first status writer it hears: the unit's, before the forger writes
    wait_until(lambda: robot.status is not None, 10, what="the unit's status at the EM")
    real = client.status.last
    assert real is not None and real.state_current_name == "STOPPED"
    forger = ros.node.create_publisher(Status, f"/{cell_name}/u/status", qos.STATUS)
    deadline = time.monotonic() + 10
    while forger.get_subscription_count() < 2:  # the robot and the test's own client
        assert time.monotonic() < deadline, "the forger never matched the EM"
        time.sleep(0.01)
    forged = Status(state_current=int(State.RESETTING), state_current_name="RESETTING", sequence=real.sequence + 1,
                    unit_mode_current=real.unit_mode_current)  # fmt: skip
    forged.equipment_modules = list(real.equipment_modules)
    for entry in forged.equipment_modules:
        entry.state_complete = False  # the unit waits for this EM's Resetting
    forger.publish(forged)
    deadline = time.monotonic() + 10
    while robot.refused_statuses < 1 and not robot.names():  # refused, or followed
        assert time.monotonic() < deadline, "the forged status was neither refused nor followed"
        time.sleep(0.01)
    assert robot.names() == [] and robot.state.name == "STOPPED", robot.names()
    client.trigger("reset")  # the real unit's Resetting runs the hook
    client.wait_state("IDLE")
    assert robot.names() == [f"resetting {real.sequence + 1}"]


def test_stop_during_a_move_then_another_ems_alarm_does_not_cut_the_move(
    ros, tmp_path: Path
) -> None:
    """Issue 26: Stop during a move wrapped in ``ctx.finish``, then 0.5 s later an alarm raised by
    another EM of the unit. Each new status used to cancel the hook again, and the second cancel
    killed the wait for the move: the move was cut and ``on_stopping`` started mid-move."""

    class Arm(Recorder):
        async def execute(self, ctx: StateContext) -> None:
            while True:
                await ctx.finish(self.move())

        async def move(self) -> None:
            self.note("move begin")
            try:
                await asyncio.sleep(1.5)
            except asyncio.CancelledError:
                self.note("move cut")
                raise
            self.note("move end")

        async def on_stopping(self, ctx: StateContext) -> None:
            self.note("stopping")

    cell_file, cell_name = write_cell(
        tmp_path,
        {"u": {"em_lease": 2.0, "equipment_modules": {"arm": {}, "camera": {}},
               "alarms": [{"id": 600, "message": "guard open", "category": 3}]}},
    )  # fmt: skip
    client = start_unit(ros, cell_file, cell_name)
    arm = em(ros, Arm, cell_name, "arm")
    camera = em(ros, Recorder, cell_name, "camera")
    online(client, "arm")
    online(client, "camera")
    to_execute(client)
    wait_note(arm, "move begin")
    assert client.trigger("stop").success
    stopping_at = client.wait_state("STOPPING")
    time.sleep(0.5)  # the reported timing: the other EM's alarm half a second into Stopping
    camera.raise_alarm(600)
    client.alarms.wait_for(lambda a: any(x.id == 600 for x in a.alarms), 5, "the camera's alarm")
    client.wait_state("STOPPED", timeout=10)
    names = arm.names()
    assert "move cut" not in names, names
    last_begin = max(i for i, n in enumerate(names) if n == "move begin")
    assert names[last_begin:] == ["move begin", "move end", "stopping"], names
    assert arm.when("move end") >= arm.when("move begin") + 1.5
    assert stopping_at.state_current_name == "STOPPING"


def test_an_em_that_hears_no_status_from_a_unit_on_the_graph_says_so(ros, tmp_path: Path) -> None:
    """A unit's status writer on the graph whose status never reaches the EM (here: a writer
    that can never match it, best effort against the EM's reliable reader) is said once after
    SILENCE leases; a unit that is not there yet is no news."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from packml_ros2.equipment_module import RESUBSCRIBE, SILENCE

    _, cell_name = write_cell(tmp_path, {"u": {"equipment_modules": {"robot": {}}}})
    robot = em(ros, Resetter, cell_name, lease=0.4)
    time.sleep(SILENCE * 0.4 + 0.5)  # longer than the silence allowed: nobody writes yet
    assert not robot.silence_warned
    deaf = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
    writer = ros.node.create_publisher(Status, f"/{cell_name}/u/status", deaf)
    seen = time.monotonic()
    wait_until(lambda: robot.silence_warned, 10, what="the EM saying it hears nothing")
    assert time.monotonic() - seen >= SILENCE * 0.4 - 0.3  # counted from the writer's arrival
    assert robot.status is None and writer.get_subscription_count() == 0
    # it subscribes again, every SILENCE leases, RESUBSCRIBE times at most
    wait_until(lambda: robot.status_resubscribed == RESUBSCRIBE, 10, what="the resubscriptions")
    time.sleep(SILENCE * 0.4 + 0.3)
    assert robot.status_resubscribed == RESUBSCRIBE


def test_an_em_deaf_to_its_units_status_subscribes_again_and_follows(ros, cell) -> None:
    """Seen in CI: an EM whose reader never got the status of the unit that had its
    heartbeats (the unit stuck in Resetting, waiting for it). Here its first reader drops
    everything: the EM subscribes again after SILENCE leases and follows the unit."""

    class DeafFirst(Resetter):
        def _subscribe_status(self):  # type: ignore[no-untyped-def]
            if getattr(self, "_deafened", False):
                return super()._subscribe_status()
            self._deafened = True
            status = interface.TOPIC["status"]
            return self.create_subscription(
                status.type, status.name, lambda *_: None, status.qos, raw=True
            )

    cell_name, client = cell
    robot = em(ros, DeafFirst, cell_name, lease=0.4)
    online(client)
    wait_until(lambda: robot.status is not None, 10, what="the status through the new reader")
    assert robot.silence_warned and robot.status_resubscribed == 1
    client.trigger("reset")
    client.wait_state("IDLE")
    assert robot.names()[-1].startswith("resetting")


def test_an_em_that_follows_its_unit_says_nothing_of_silence(ros, cell) -> None:
    from packml_ros2.equipment_module import SILENCE

    cell_name, _client = cell
    robot = em(ros, Resetter, cell_name, lease=0.4)
    wait_until(lambda: robot.status is not None, 10, what="the unit's status at the EM")
    time.sleep(SILENCE * 0.4 + 0.5)
    assert not robot.silence_warned
