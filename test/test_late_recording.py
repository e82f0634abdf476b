"""Issue 16: a recording started at any moment replays — offline cases, on recordings made by
driving an engine exactly as the unit node does (bag/synthetic.py), including what a recorder
that joins late receives (the publishers' history) and the snapshot the unit publishes then.
The real processes and DDS are in test/ros/test_late_recording.py."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from packml_interfaces.msg import EmReport, UnitSnapshot
from rclpy.serialization import deserialize_message, serialize_message

from packml_ros2.bag.recording import RecordingError, load
from packml_ros2.bag.replay import replay, update
from packml_ros2.bag.synthetic import SyntheticUnit
from packml_ros2.core import Cmd, State, load_cell
from test.test_replay import packml, rewrite

ROOT = Path(__file__).resolve().parents[1]
CELL_FILE = ROOT / "test" / "bags" / "cell.yaml"
CONFIG = load_cell(CELL_FILE).units["robot_cell"]
EMS = [em.name for em in CONFIG.equipment_modules]
NEXT = {State.STOPPED: Cmd.RESET, State.IDLE: Cmd.START, State.HELD: Cmd.UNHOLD,
        State.ABORTED: Cmd.CLEAR, State.COMPLETE: Cmd.RESET}  # fmt: skip


def production(sim: SyntheticUnit, t: float, until: float) -> float:
    """The operator keeps the unit producing, its EMs report State Complete, count, beat (every
    0.5 s), now and then the robot's E-stop or a Hold: from ``t`` to ``until`` seconds."""
    unit = sim.unit
    n = 0
    while t < until:
        n += 1
        t += 0.1
        if n % 5 == 0:
            for em in EMS:
                sim.report(t, em, EmReport.KIND_HEARTBEAT)
        cmd = NEXT.get(unit.state)
        if cmd is not None:
            if unit.state is State.ABORTED:
                sim.report(t, "robot", EmReport.KIND_ALARM, alarm_id=1, alarm_active=False)
            sim.call(t, unit.command, cmd)
        elif unit.state is State.EXECUTE:
            sim.report(t, "infeed", EmReport.KIND_COUNT, counter=EmReport.COUNTER_CONSUMED, increment=1)  # fmt: skip
            if n % 37 == 0:
                sim.call(t, unit.command, Cmd.HOLD)
            elif n % 89 == 0:
                sim.report(t, "robot", EmReport.KIND_ALARM, alarm_id=1, alarm_active=True)
        elif unit.state.name.endswith("ING"):
            state, seq = int(unit.state), unit.sequence
            for em in EMS:
                sim.report(t, em, EmReport.KIND_STATE_COMPLETE, state=state, sequence=seq)
    return t


def late_recording(
    path: Path, inputs: int = 6000, after: float = 10.0, **write: Any
) -> SyntheticUnit:
    """A unit that has applied ``inputs`` inputs when a recorder joins and records ``after``
    seconds of production, then stops."""
    sim = SyntheticUnit(CONFIG, CELL_FILE.read_text(), persistence=True)
    t = 0.0
    for em in EMS:
        sim.report(0.01, em, EmReport.KIND_HEARTBEAT)
    while sim._index < inputs:
        t = production(sim, t, t + 10.0)
    joined = t + 0.05
    sim.advance(joined)
    sim.snapshot()
    t = production(sim, joined, joined + after)
    sim.advance(t + 0.3)
    sim.write(path, joined=write.pop("joined", joined), stop=write.pop("stop", t + 0.3), **write)
    return sim


@pytest.fixture(scope="module")
def late(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("late") / "bag"
    late_recording(path)
    return path


def test_a_recording_that_joined_late_replays_from_the_snapshot(late: Path) -> None:
    rec = load(late).unit("robot_cell")
    first = min(i.index for i in rec.inputs)
    assert first > 1000 and rec.inputs[0].name != "start"  # the input log's history: 5000 deep
    (snap,) = rec.snapshots
    assert snap.index > first
    result = replay(late).assert_matches()
    u = result.units[0]
    assert u.origin.index == snap.index and u.origin.start is None
    assert u.inputs[0].index == snap.index + 1
    assert u.compared["transitions"] > 10 and u.compared["admin"] > 5
    # the latched history the recorder got when it joined was published before the snapshot
    assert u.before_origin["transitions"] == 100 and u.before_origin["status"] == 1
    assert "from a snapshot after input #" in result.summary()
    out = packml("replay", str(late))
    assert out.returncode == 0 and "match" in out.stdout, out.stdout + out.stderr


def test_without_the_recorders_notes_the_outputs_align_by_content(late: Path) -> None:
    rec = load(late)
    for unit in rec.units.values():
        unit.publications.clear()
    replay(late, recording=rec).assert_matches()


def test_the_end_of_a_late_recording_is_checked(late: Path, tmp_path: Path) -> None:
    counts = {t: len(msgs) for t, msgs in load(late).unit("robot_cell").outputs.items()}
    for topic in ("transitions", "status"):
        dst = tmp_path / topic
        last = counts[topic] - 1
        rewrite(late, dst, drop=lambda t, i, raw, topic=topic, last=last: t.endswith(f"/{topic}") and i == last)  # fmt: skip
        (d,) = replay(dst).differences
        assert (d.topic, d.kind) == (topic, "extra")


def test_the_earliest_usable_snapshot_is_the_origin(tmp_path: Path) -> None:
    """A snapshot older than the input log's history (the last one a previous recorder got) is
    passed over for the one the unit published when this recorder joined; a recording from the
    unit's start replays from its start even with snapshots in it."""
    sim = SyntheticUnit(CONFIG, CELL_FILE.read_text())
    for em in EMS:
        sim.report(0.01, em, EmReport.KIND_HEARTBEAT)
    sim.snapshot()  # a recorder joined at once ...
    t = production(sim, 0.0, 20.0)
    sim.snapshot()  # ... and another one, later
    early = sim._index
    while sim._index < early + 5200:
        t = production(sim, t, t + 10.0)
    joined = t + 0.01
    sim.advance(joined)
    sim.snapshot()
    t = production(sim, joined, joined + 5.0)
    sim.advance(t + 0.2)
    sim.write(tmp_path / "late", joined=joined, stop=t + 0.2)
    rec = load(tmp_path / "late").unit("robot_cell")
    assert len(rec.snapshots) == 2  # the previous one (history) and the fresh one
    u = replay(tmp_path / "late").assert_matches().units[0]
    assert u.origin.index == max(s.index for s in rec.snapshots)
    sim.write(tmp_path / "all", stop=t + 0.2)
    u = replay(tmp_path / "all").assert_matches().units[0]
    assert u.origin.start is not None and u.inputs[0].name == "start"


def test_an_idle_unit_recorded_late_replays(tmp_path: Path) -> None:
    """No input at all after the snapshot (the unit stopped, its EMs only beat): the deadlines
    (admin heartbeats) are the outputs."""
    sim = SyntheticUnit(CONFIG, CELL_FILE.read_text())
    for em in EMS:
        sim.report(0.01, em, EmReport.KIND_HEARTBEAT)
    t = 0.0
    while sim._index < 5200:
        t = production(sim, t, t + 10.0)
    sim.call(t, sim.unit.command, Cmd.STOP)
    for em in EMS:
        sim.report(t + 0.2, em, EmReport.KIND_STATE_COMPLETE, state=int(State.STOPPING), sequence=sim.unit.sequence)  # fmt: skip
    assert sim.unit.state is State.STOPPED
    joined = t + 1.0
    sim.advance(joined)
    sim.snapshot()
    inputs = sim._index
    for k in range(60):  # 30 s of heartbeats: alive EMs are no inputs
        for em in EMS:
            sim.report(joined + 0.5 * k, em, EmReport.KIND_HEARTBEAT)
    assert sim._index == inputs
    sim.write(tmp_path / "idle", joined=joined, stop=joined + 30.0)
    u = replay(tmp_path / "idle").assert_matches().units[0]
    assert u.inputs == [] and u.compared["admin"] >= 5


def test_update_of_a_late_recording_keeps_it_replaying(late: Path, tmp_path: Path) -> None:
    result, dst = update(late, tmp_path / "updated")
    assert result.ok
    replay(dst).assert_matches()
    assert load(dst).unit("robot_cell").snapshots


def _with_snapshot(src: Path, dst: Path, edit: Any) -> None:
    def change(topic: str, i: int, raw: bytes) -> bytes:
        if topic.endswith("/snapshot"):
            m = deserialize_message(raw, UnitSnapshot)
            if callable(edit):
                state = json.loads(m.state_json)
                edit(state)
                m.state_json = json.dumps(state)
            else:
                m.state_json = edit
            return bytes(serialize_message(m))
        return raw

    rewrite(src, dst, change)


@pytest.mark.parametrize(
    ("edit", "reason"),
    [
        ("{not json", "is not JSON"),
        ("[1, 2]", "holds no engine state"),
        (lambda s: s.update(schema=2), "has schema 2; this version reads 1"),
        (lambda s: s["engine"].update(schema=7), "snapshot schema 7: this version reads schema 1"),
        (lambda s: s["published"].pop("admin"), "does not say how many messages"),
        (lambda s: s["engine"]["machine"].update(mode=99), "mode 99 is not configured"),
        (lambda s: s["engine"].pop("deadlines"), "cannot be restored: KeyError"),
    ],
)  # fmt: skip
def test_a_snapshot_that_cannot_be_used_is_a_bag_that_cannot_be_replayed(
    late: Path, tmp_path: Path, edit: Any, reason: str
) -> None:
    bad = tmp_path / "bad"
    _with_snapshot(late, bad, edit)
    with pytest.raises(RecordingError, match="snapshot"):
        replay(bad)
    out = packml("replay", str(bad))
    assert out.returncode == 2, out.stdout + out.stderr
    assert reason in out.stderr and "Traceback" not in out.stderr, out.stderr


def test_live_replay_needs_a_recording_from_the_start(late: Path) -> None:
    out = packml("replay", str(late), "--live", "--timeout", "1")
    assert out.returncode == 2 and "--live drives a freshly started unit" in out.stderr
