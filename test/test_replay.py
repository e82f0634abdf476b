"""Issue 6: record and replay — bag-driven regression tests.

The bags in test/bags/ were recorded from real unit and EM processes over DDS
(tools/record_test_bags.py); independent_writer.mcap holds the same topics written by the ``mcap``
and ``mcap-ros2-support`` packages. Every bag replays offline to the recorded outputs, identically
every time; a tampered bag fails with the first diverging transition and the inputs behind it;
``--update`` rewrites it; the CLI verbs record and replay real nodes.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import struct
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from packml_interfaces.msg import Admin, AlarmList, Status, TransitionEvent, UnitInput
from rclpy.serialization import deserialize_message, serialize_message

from packml_ros2.bag import cdr
from packml_ros2.bag.recording import RecordingError, load
from packml_ros2.bag.replay import replay, update
from packml_ros2.bag.topics import CUSTOM_KEY, typestore
from packml_ros2.bag.upgrade import definition_store

ROOT = Path(__file__).resolve().parents[1]
BAGS = ROOT / "test" / "bags"
PACKML = [sys.executable, "-m", "packml_ros2.cli.main"]
RECORDED = sorted(p.name for p in BAGS.iterdir() if p.is_dir())
ALL_BAGS = [*RECORDED, "independent_writer.mcap"]
#: recorded before the input log schema (issue 14); shift was recorded with schema 1
SCHEMA_0 = {"normal_production", "hold_unhold", "suspend_interlock", "alarm_stop",
            "alarm_abort_clear_reset", "mode_changes", "em_lost"}  # fmt: skip
SCENARIOS = SCHEMA_0 | {"shift"}


def packml(*args: str, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*PACKML, *args], capture_output=True, text=True, timeout=timeout, cwd=ROOT, check=False
    )


def rewrite(src: Path, dst: Path, change: Any = None, drop: Any = None, custom: bool = True,
            add: Any = None) -> None:  # fmt: skip
    """Copy bag ``src`` to ``dst`` (rosbags), ``change(topic, index, raw) -> raw`` per message,
    ``drop(topic, index, raw) -> bool``, ``add(topic, index, raw) -> [raw]`` written after it (1 ns
    apart); ``custom=False`` leaves out the recorder's notes."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import Writer

    seen: dict[str, int] = {}
    with AnyReader([src]) as reader:
        writer = Writer(dst, version=9)
        writer.open()
        conns = {c.topic: writer.add_connection(c.topic, c.msgtype, typestore=reader.typestore,
                                                offered_qos_profiles=c.ext.offered_qos_profiles)
                 for c in reader.connections}  # fmt: skip
        for conn, ts, data in reader.messages():
            i = seen[conn.topic] = seen.get(conn.topic, -1) + 1
            raw = bytes(data)
            if drop is not None and drop(conn.topic, i, raw):
                continue
            writer.write(
                conns[conn.topic], ts, raw if change is None else change(conn.topic, i, raw)
            )
            for n, extra in enumerate(add(conn.topic, i, raw) if add is not None else [], 1):
                writer.write(conns[conn.topic], ts + n, extra)
        notes = (
            reader.readers[0].storage.metadata.custom
            if hasattr(reader.readers[0], "storage")
            else None
        )
        if custom and notes and CUSTOM_KEY in notes:
            writer.set_custom_data(CUSTOM_KEY, notes[CUSTOM_KEY])
        writer.close()


# -- every bag replays --------------------------------------------------------------------------------
def test_the_scenarios_are_all_there() -> None:
    assert set(RECORDED) >= SCENARIOS, f"missing bags: {SCENARIOS - set(RECORDED)}"
    assert (BAGS / "independent_writer.mcap").is_file()


@pytest.mark.parametrize("bag", ALL_BAGS)
def test_bag_replays_to_the_recorded_outputs(packml_replay: Any, bag: str) -> None:
    result = packml_replay(f"test/bags/{bag}").assert_matches()
    unit = result.units[0]
    assert unit.inputs[0].name == "start"
    assert set(unit.compared) == {"transitions", "status", "alarms", "admin"}
    assert all(n > 0 for n in unit.compared.values()), unit.compared


def test_bags_recorded_before_the_input_log_schema_replay() -> None:
    """Most bags of test/bags were recorded with schema 0 (the engine's method names): they are
    read through inputlog.upgrade, and replay (test above)."""
    from packml_ros2.core import inputlog

    for bag in RECORDED:
        inputs = next(iter(load(BAGS / bag).units.values())).inputs
        start = next(i for i in inputs if i.name == "start")
        assert inputlog.schema_of(start.args) == (0 if bag in SCHEMA_0 else 1), bag
        if bag not in SCHEMA_0:
            continue
        assert any(i.name == "em_complete" for i in inputs), bag  # a schema 0 name
        assert any(i.name == "em.state_complete" for i in replay(BAGS / bag).units[0].inputs)


def test_a_users_regression_test_is_three_lines(packml_replay: Any) -> None:
    packml_replay("test/bags/normal_production").assert_matches()


def test_the_scenarios_do_what_their_names_say() -> None:
    def transitions(bag: str) -> list[str]:
        produced = replay(BAGS / bag).units[0].produced["transitions"]
        return [f"{m.to_state_name}:{m.trigger_name}" for m in produced]

    assert "EXECUTE:STATE_COMPLETE" in transitions("normal_production")
    assert {"HELD:STATE_COMPLETE", "UNHOLDING:COMMAND"} <= set(transitions("hold_unhold"))
    assert {"SUSPENDING:INTERLOCK", "UNSUSPENDING:INTERLOCK"} <= set(
        transitions("suspend_interlock")
    )
    assert "STOPPING:ALARM" in transitions("alarm_stop")
    assert {"ABORTING:ALARM", "CLEARING:COMMAND", "RESETTING:COMMAND"} <= set(
        transitions("alarm_abort_clear_reset")
    )
    assert transitions("mode_changes").count("STOPPED:MODE") == 3
    assert "ABORTING:EM_LOST" in transitions("em_lost")
    # shift: what the short bags do not hold (the mutation score of test_mutations needs it)
    u = replay(BAGS / "shift").units[0]
    assert any(e.stale_reports for m in u.produced["status"] for e in m.equipment_modules)
    assert any(m.mode_change_not_allowed for m in u.produced["status"])
    assert {i.name for i in u.inputs} >= {"alarm.ack", "counters.reset", "em.lost"}
    assert transitions("shift").count("STOPPING:COMMAND") == 2
    # hold_unhold: a recorder that joined late, on a unit that restored its admin data
    u = replay(BAGS / "hold_unhold").units[0]
    assert u.inputs[0].args["document"] is not None
    assert u.windows["status"][0] > 0  # the first statuses were published before it subscribed


def test_older_definitions_replay_on_the_fields_they_have() -> None:
    """Issue 32 added the recipe and stack-light fields to Status (and EmSummary, EmReport): the
    bags recorded before replay, compared on the fields they had; a field they had still
    counts (the status mutants of test_mutations are caught on these bags)."""
    rec = load(BAGS / "normal_production")
    unit = rec.units["/demo_cell/robot_cell"]
    upgrade = unit.upgrades["status"]
    assert {"recipe_current", "stack_light", "equipment_modules.recipe_answer"} <= upgrade.absent
    assert "state_current" not in upgrade.absent
    result = replay(BAGS / "normal_production", recording=rec)
    assert result.ok, result.report()
    assert result.units[0].compared["status"] > 10
    produced = result.units[0].produced["status"][-1]
    masked = upgrade.mask(produced)
    assert masked.stack_light.colors == [] and produced.stack_light.colors  # not compared
    assert masked.state_current == produced.state_current  # compared


def test_bags_carry_metadata_qos_and_type_definitions() -> None:
    from rosbags.highlevel import AnyReader

    for bag, storage in (("normal_production", "mcap"), ("alarm_stop", "sqlite3")):
        meta = (BAGS / bag / "metadata.yaml").read_text()
        assert f"storage_identifier: {storage}" in meta
        with AnyReader([BAGS / bag]) as reader:
            by_topic = {c.topic: c for c in reader.connections}
            status = by_topic["/demo_cell/robot_cell/status"]
            assert status.msgdef.data  # the definition is stored: other tools decode it
            # the digest is the stored definition's (these bags predate the recipe fields of
            # Status: an older definition, which replay upgrades, test_older_definitions_replay)
            stored = definition_store(status.msgtype, "MSG", status.msgdef.data)
            assert status.digest == stored.hash_rihs01("packml_interfaces/msg/Status")
            assert status.digest != typestore().hash_rihs01("packml_interfaces/msg/Status")
            assert status.ext.offered_qos_profiles[0].durability.name == "TRANSIENT_LOCAL"
            assert {t.rsplit("/", 1)[1] for t in by_topic} == {
                "input_log",
                "config",
                "status",
                "transitions",
                "admin",
                "alarms",
                "em_reports",
            }


def test_bags_written_here_name_the_ros_distribution(tmp_path: Path) -> None:
    """metadata.yaml (and the storage file's copy of it) says ``ros_distro: kilted``, as
    rosbag2 writes its distribution, not ``rosbags``; mcap chunks are zstd-compressed."""
    _, dst = update(BAGS / "normal_production", tmp_path / "mcap")
    _, db = update(BAGS / "alarm_stop", tmp_path / "db")
    for bag in (dst, db):
        meta = (bag / "metadata.yaml").read_text()
        assert "ros_distro: kilted" in meta and "rosbags" not in meta.split("ros_distro:")[1]
    raw = (dst / "mcap.mcap").read_bytes()
    # the storage's metadata record (outside the chunks) names the distribution too ...
    assert b"ros_distro: kilted" in raw and b"ros_distro: rosbags" not in raw
    # ... and the messages are in zstd chunks: the config's text is not in the file as such,
    # though a reader gets it back (rosbags decompresses)
    assert b"zstd" in raw and b"\x28\xb5\x2f\xfd" in raw  # the compression, a zstd frame
    assert b"pick-and-place" not in raw
    config = next(iter(load(dst).units.values())).config_json or ""
    assert "pick-and-place" in config
    import sqlite3

    with sqlite3.connect(db / "db.db3") as conn:
        (stored,) = conn.execute("SELECT metadata FROM metadata").fetchone()
    assert "ros_distro: kilted" in stored


def test_alignment_by_content_when_the_bag_has_no_recorder_notes() -> None:
    rec = load(BAGS / "hold_unhold")
    for unit in rec.units.values():
        unit.publications.clear()
    result = replay(BAGS / "hold_unhold", recording=rec).assert_matches()
    assert result.units[0].windows["status"][0] > 0


# -- determinism -----------------------------------------------------------------------------------------
def test_replay_is_deterministic_ten_times_out_of_ten() -> None:
    for bag in ALL_BAGS:
        results = [replay(BAGS / bag) for _ in range(10)]
        assert all(r.ok for r in results), bag
        assert len({r.digest() for r in results}) == 1, bag
        admin_times = {
            tuple((tuple(m.state_cumulative_time), tuple(m.mode_cumulative_time), m.stamp.sec, m.stamp.nanosec)
                  for m in r.units[0].produced["admin"])
            for r in results
        }  # fmt: skip
        assert len(admin_times) == 1, bag


def test_replay_is_deterministic_across_processes_and_hash_seeds() -> None:
    here = replay(BAGS / "em_lost").digest()
    code = (
        "import sys; from packml_ros2.bag.replay import replay; print(replay(sys.argv[1]).digest())"
    )
    for seed in ("0", "12345"):
        env = {**os.environ, "PYTHONHASHSEED": seed}
        out = subprocess.run([sys.executable, "-c", code, str(BAGS / "em_lost")], capture_output=True,
                             text=True, env=env, timeout=60, check=True)  # fmt: skip
        assert out.stdout.strip() == here


# -- differences, refusals, --update ---------------------------------------------------------------------
def _tamper_status(tmp_path: Path) -> Path:
    bad = tmp_path / "tampered"

    def change(topic: str, i: int, raw: bytes) -> bytes:
        if topic.endswith("/transitions") and i == 4:  # STARTING -> EXECUTE becomes -> HELD
            m = deserialize_message(raw, TransitionEvent)
            m.to_state, m.to_state_name = 11, "HELD"
            return bytes(serialize_message(m))
        return raw

    rewrite(BAGS / "normal_production", bad, change)
    return bad


def test_a_tampered_output_fails_with_the_diverging_transition_and_its_inputs(
    tmp_path: Path,
) -> None:
    result = replay(_tamper_status(tmp_path))
    assert not result.ok
    text = result.report()
    assert "MISMATCH" in text
    assert "first difference: robot_cell/transitions: message #4" in text
    assert "to_state: recorded 11 (HELD), replayed 6 (EXECUTE)" in text
    assert "diverging transition:" in text
    assert "recorded: seq 5 STARTING -> HELD" in text
    assert "replayed: seq 5 STARTING -> EXECUTE" in text
    assert "last common transition: seq 4 IDLE -> STARTING [COMMAND 2 from operator]" in text
    assert "inputs that led to it" in text
    assert 'em.state_complete {"em":' in text  # the EMs' State Complete reports of Starting
    with pytest.raises(AssertionError, match="diverging transition"):
        result.assert_matches()


def test_exit_codes_tell_a_mismatch_from_a_bag_that_cannot_be_replayed(tmp_path: Path) -> None:
    """0 match, 1 mismatch, 2 not a PackML recording, 4 truncated or corrupt, 7 incomplete: one
    line saying why, no traceback."""
    assert packml("replay", str(BAGS / "normal_production")).returncode == 0
    mismatch = packml("replay", str(_tamper_status(tmp_path)))
    assert mismatch.returncode == 1 and "MISMATCH" in mismatch.stdout

    def bag_copy(name: str, src: str = "normal_production") -> Path:
        dst = tmp_path / name
        shutil.copytree(BAGS / src, dst)
        return dst

    unusable: dict[str, tuple[Path, str, int]] = {}
    for src, suffix in (("normal_production", "mcap"), ("alarm_stop", "db3")):
        bag = bag_copy(f"truncated_{suffix}", src)
        f = bag / f"{src}.{suffix}"
        f.write_bytes(f.read_bytes()[: f.stat().st_size // 2])
        unusable[f"truncated {suffix}"] = (bag, "cannot read the bag", 4)
        bag = bag_copy(f"corrupt_{suffix}", src)
        f = bag / f"{src}.{suffix}"
        f.write_bytes(bytes(range(256)) * 64)
        unusable[f"corrupt {suffix}"] = (bag, "cannot read the bag", 4)
    foreign = tmp_path / "foreign"
    from rosbags.rosbag2 import Writer
    from std_msgs.msg import String

    writer = Writer(foreign, version=9)
    writer.open()
    conn = writer.add_connection("/chatter", "std_msgs/msg/String", typestore=typestore())
    writer.write(conn, 1, bytes(serialize_message(String(data="hi"))))
    writer.close()
    unusable["foreign"] = (foreign, "no PackML unit topics", 2)
    rewrite(BAGS / "normal_production", tmp_path / "gap",
            drop=lambda t, i, raw: t.endswith("/input_log") and i == 7)  # fmt: skip
    unusable["incomplete"] = (tmp_path / "gap", "inputs #8..#8 are missing", 7)
    for what, (bag, reason, code) in unusable.items():
        out = packml("replay", str(bag))
        assert out.returncode == code, (what, out.returncode, out.stdout, out.stderr)
        assert reason in out.stderr and "Traceback" not in out.stderr, (what, out.stderr)
        assert out.stderr.count("\n") == 1, (what, out.stderr)


def test_the_diverging_line_agrees_with_the_field_differences(tmp_path: Path) -> None:
    """A hand-edited bag whose state number and name disagree: the diverging transition names
    states by their numbers, as the field differences above it do, and says what the message
    calls them."""
    bad = tmp_path / "number_only"

    def change(topic: str, i: int, raw: bytes) -> bytes:
        if topic.endswith("/transitions") and i == 4:  # STARTING -> EXECUTE, number edited only
            m = deserialize_message(raw, TransitionEvent)
            m.to_state = 11
            return bytes(serialize_message(m))
        return raw

    rewrite(BAGS / "normal_production", bad, change)
    text = replay(bad).report()
    assert "to_state: recorded 11 (HELD), replayed 6 (EXECUTE)" in text
    assert "recorded: seq 5 STARTING -> HELD (named 'EXECUTE' in the message)" in text
    assert "replayed: seq 5 STARTING -> EXECUTE [STATE_COMPLETE" in text


def test_update_rewrites_the_expected_outputs(tmp_path: Path) -> None:
    bad = _tamper_status(tmp_path)
    assert packml("replay", str(bad), "--check").returncode == 1
    out = packml("replay", str(bad), "--update")
    assert out.returncode == 0, out.stderr
    assert "updated" in out.stdout
    again = packml("replay", str(bad))
    assert again.returncode == 0, again.stdout + again.stderr
    assert "match" in again.stdout
    assert replay(bad).digest() == replay(BAGS / "normal_production").digest()
    # in place, the storage file keeps the bag's name (it was named after a temporary directory)
    assert sorted(p.stem for p in bad.iterdir()) == ["metadata", bad.name]
    assert not any(p.name.endswith(".update-tmp") for p in bad.parent.iterdir())
    # into another bag, as sqlite3 from an mcap file
    result, dst = update(BAGS / "independent_writer.mcap", tmp_path / "copy", storage="sqlite3")
    assert result.ok and "sqlite3" in (dst / "metadata.yaml").read_text()
    replay(dst).assert_matches()


def test_other_output_differences_are_found_too(tmp_path: Path) -> None:
    def admin_change(topic: str, i: int, raw: bytes) -> bytes:
        if topic.endswith("/admin") and i == 3:
            m = deserialize_message(raw, Admin)
            m.acc_time_since_reset += 1
            return bytes(serialize_message(m))
        return raw

    rewrite(BAGS / "alarm_stop", tmp_path / "a", admin_change)
    result = replay(tmp_path / "a")
    (d,) = result.differences
    assert (d.topic, d.kind, d.recorded_index) == ("admin", "differs", 3)
    assert [f[0] for f in d.fields] == ["acc_time_since_reset"]
    assert "transitions agree up to the difference" in result.report()

    # a recorded message the replay does not produce, and one it produces that was not recorded
    rewrite(
        BAGS / "alarm_stop", tmp_path / "b", drop=lambda t, i, raw: t.endswith("/alarms") and i == 1
    )
    (d,) = replay(tmp_path / "b").differences
    assert d.topic == "alarms" and d.kind == "differs"
    rewrite(BAGS / "alarm_stop", tmp_path / "c", custom=False,
            drop=lambda t, i, raw: t.endswith("/alarms") and i == 1)  # fmt: skip
    (d,) = replay(tmp_path / "c").differences
    assert d.topic == "alarms"

    def extra(topic: str, i: int, raw: bytes) -> bytes:
        if topic.endswith("/alarms") and i == 0:
            m = deserialize_message(raw, AlarmList)
            m.banner = "not what the unit said"
            return bytes(serialize_message(m))
        return raw

    rewrite(BAGS / "alarm_stop", tmp_path / "d", extra)
    (d,) = replay(tmp_path / "d").differences
    assert d.fields == [("banner", "not what the unit said", "")]


@pytest.mark.parametrize("bag", ALL_BAGS)
def test_the_end_of_a_recording_is_checked(tmp_path: Path, bag: str) -> None:
    """Up to the recorder's stop, every output counts: deleting the last transition, status,
    alarm list or admin message of a bag is a difference, and so is a status the unit never
    published added at the end (a copy of the last, 1 ms later)."""
    src = BAGS / bag
    counts = {t.rsplit("/", 1)[1]: n for t, n in _topic_counts(src).items()}
    for topic in ("transitions", "status", "alarms", "admin"):
        last = counts[topic] - 1
        dst = tmp_path / f"no_last_{topic}"
        rewrite(src, dst, drop=lambda t, i, raw, topic=topic, last=last: t.endswith(f"/{topic}") and i == last)  # fmt: skip
        result = replay(dst)
        assert not result.ok, f"{bag}: the last {topic} message deleted, and it still matches"
        (d,) = result.differences
        assert d.topic == topic and d.kind == "extra", d

    def later(raw: bytes) -> bytes:
        # (the stamp leads the message, after the 4-byte CDR header: the bytes of any version)
        assert raw[:2] == b"\x00\x01"  # little-endian CDR
        sec, nanosec = struct.unpack_from("<iI", raw, 4)
        nanosec += 1_000_000
        if nanosec >= 1_000_000_000:
            sec, nanosec = sec + 1, nanosec - 1_000_000_000
        return raw[:4] + struct.pack("<iI", sec, nanosec) + raw[12:]

    dst = tmp_path / "one_more_status"
    rewrite(src, dst, add=lambda t, i, raw: [later(raw)] if t.endswith("/status") and i == counts["status"] - 1 else [])  # fmt: skip
    result = replay(dst)
    assert not result.ok, f"{bag}: a status added at the end, and it still matches"
    assert result.differences[0].topic == "status"


def _topic_counts(bag: Path) -> dict[str, int]:
    from rosbags.highlevel import AnyReader

    with AnyReader([bag]) as reader:
        return {c.topic: c.msgcount for c in reader.connections}


def test_incomplete_input_logs_are_refused(tmp_path: Path) -> None:
    rewrite(BAGS / "normal_production", tmp_path / "gap",
            drop=lambda t, i, raw: t.endswith("/input_log") and i == 7)  # fmt: skip
    with pytest.raises(RecordingError, match=r"gap: inputs #8\.\.#8 are missing"):
        replay(tmp_path / "gap")
    rewrite(BAGS / "normal_production", tmp_path / "late",
            drop=lambda t, i, raw: t.endswith("/input_log") and i < 3)  # fmt: skip
    with pytest.raises(RecordingError, match=r"begins at input #4, not at the unit's start"):
        replay(tmp_path / "late")
    out = packml("replay", str(tmp_path / "late"))
    assert out.returncode == 7 and "not at the unit's start" in out.stderr  # inputs missing


def test_the_fast_comparison_ignores_padding_only() -> None:
    """Serialized messages are compared with their padding ignored (cdr.same_bytes); flipping
    any data byte must be noticed, flipping a padding byte must not."""
    rec = load(BAGS / "alarm_abort_clear_reset").unit("robot_cell")
    for topic, cls in (("status", Status), ("transitions", TransitionEvent), ("alarms", AlarmList),
                       ("admin", Admin)):  # fmt: skip
        raw = rec.outputs[topic][-1]
        again = bytes(serialize_message(deserialize_message(raw, cls)))
        assert cdr.same_bytes(raw, again, cls)
        gaps: list[tuple[int, int]] = []
        end = cdr.walker_of(cls)(memoryview(raw)[4:], 0, gaps, cdr._U32[True], [])
        padding = {4 + i for s, e in gaps for i in range(s, e)} | set(range(4 + end, len(raw)))
        for i in range(4, len(raw)):
            flipped = bytearray(raw)
            flipped[i] ^= 0x40
            assert cdr.same_bytes(raw, bytes(flipped), cls) == (i in padding), (topic, i)


def test_our_serializer_gives_rclpys_bytes() -> None:
    """cdr.serialize (used for the comparison of every output) gives the bytes of
    rclpy.serialization with the padding zeroed, for every message of a few replays."""
    for bag in ("alarm_abort_clear_reset", "mode_changes", "suspend_interlock"):
        unit = replay(BAGS / bag).units[0]
        for topic, msgs in unit.produced.items():
            cls = type(msgs[0])
            for m in msgs:
                assert cdr.serialize(m) == cdr.canonical(bytes(serialize_message(m)), cls), topic


# -- command line -------------------------------------------------------------------------------------------
def test_the_input_log_reader_gives_rclpys_values() -> None:
    """cdr.read_unit_input (loading input logs) decodes what rclpy decodes; other encodings and
    broken buffers are left to rclpy (None)."""
    cases = [("filler", "command", '{"cmd": 2, "source": "operator"}', 1, 0, 5),
             ("", "em_seen", "", 2**40 + 3, -5, 999_999_999),
             ("ünit", "step" * 70, '{"é": "ü"}', 17, 2**31 - 1, 1)]  # fmt: skip
    for unit, name, args, index, sec, nanosec in cases:
        m = UnitInput(unit=unit, name=name, args_json=args, index=index)
        m.stamp.sec, m.stamp.nanosec = sec, nanosec
        raw = bytes(serialize_message(m))
        back = deserialize_message(raw, UnitInput)
        assert cdr.read_unit_input(raw) == (back.stamp.sec, back.stamp.nanosec, back.index,
                                            back.unit, back.name, back.args_json)  # fmt: skip
        assert cdr.read_unit_input(b"\x00\x00" + raw[2:]) is None  # big-endian: rclpy's job
        assert cdr.read_unit_input(raw[:-3]) is None  # truncated


def test_cli_help_and_usage_errors(tmp_path: Path) -> None:
    for verb in ("record", "replay"):
        out = packml(verb, "--help")
        assert out.returncode == 0 and "exit codes" in out.stdout
    assert packml("replay", str(tmp_path / "none")).returncode == 2
    assert packml("replay", str(BAGS / "normal_production"), "--update", "--live").returncode == 2
    assert packml("record", "a/b", "--duration", "0").returncode == 2
    sqlite = packml("record", "a/b", "--storage", "sqlite3")  # issue 27: 39 MB per hour
    assert sqlite.returncode == 2 and "MB per hour" in sqlite.stderr, sqlite.stderr
    ok = packml("replay", str(BAGS / "normal_production"), "--check")
    assert ok.returncode == 0 and "match" in ok.stdout


class Output:
    """The stderr of a running ``packml`` process, line by line, waited on with a deadline."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        import queue
        import threading

        self.proc = proc
        self.lines: queue.Queue[str] = queue.Queue()
        self.seen: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.lines.put(line)

    def wait_for(self, text: str, timeout: float = 20.0) -> None:
        import queue
        import time

        deadline = time.monotonic() + timeout
        while not any(text in line for line in self.seen):
            try:
                self.seen.append(self.lines.get(timeout=max(0.01, deadline - time.monotonic())))
            except queue.Empty:
                raise TimeoutError(f"no {text!r} from packml: {self.seen}") from None

    def rest(self) -> str:
        self.proc.wait(30)
        while not self.lines.empty():
            self.seen.append(self.lines.get())
        return "".join(self.seen)


@pytest.mark.ros
def test_cli_records_a_running_unit_and_the_bag_replays(tmp_path: Path, processes: Any) -> None:
    """``packml record`` on a unit that is already running (it joins late) while the unit is
    commanded — a cell target stopped with Ctrl-C, a cell/unit target with --duration stopped by
    SIGTERM; then ``packml replay --check``."""
    import signal

    from std_srvs.srv import Trigger

    from packml_ros2.testing.harness import RosHarness
    from test.ros.cells import start_unit_process, write_cell

    cell_file, cell = write_cell(tmp_path, {"filler": {"mach_speed": 10}})
    start_unit_process(processes, cell_file, "filler")
    ros = RosHarness(int(os.environ["ROS_DOMAIN_ID"]))
    runs = {
        "mcap": [cell, "--config", str(cell_file)],
        "unit": [f"{cell}/filler", "--storage", "mcap", "--duration", "30"],
    }
    try:
        assert ros.call(Trigger, f"/{cell}/filler/reset").success  # before the recorder runs
        for run, target in runs.items():
            bag = tmp_path / f"rec_{run}"
            proc = subprocess.Popen([*PACKML, "record", *target, "-o", str(bag)], cwd=ROOT,
                                    stderr=subprocess.PIPE, text=True)  # fmt: skip
            out = Output(proc)
            out.wait_for(f"receiving /{cell}/filler")
            for name in ("start", "hold", "unhold", "stop", "reset"):
                assert ros.call(Trigger, f"/{cell}/filler/{name}").message
            if run == "mcap":
                proc.send_signal(signal.SIGINT)  # Ctrl-C: the bag is closed cleanly
            else:
                proc.terminate()  # SIGTERM, as a service manager would
            text = out.rest()
            assert proc.returncode == 0, text
            assert "wrote" in text and "Traceback" not in text
    finally:
        ros.close()
    for run in runs:
        bag = tmp_path / f"rec_{run}"
        assert "storage_identifier: mcap" in (bag / "metadata.yaml").read_text()
        out = packml("replay", str(bag), "--check")
        assert out.returncode == 0, out.stdout + out.stderr
        unit = replay(bag).units[0]
        assert unit.compared["transitions"] >= 9  # the commands' transitions were recorded
        assert load(bag).custom["recorder"] == "packml_ros2"
    topics = (tmp_path / "rec_mcap" / "metadata.yaml").read_text()
    assert f"/{cell}/coordinator/status" in topics  # a cell: its coordinator's status too


@pytest.mark.ros
def test_cli_record_unknown_target_is_unavailable(tmp_path: Path) -> None:
    out = packml("record", "no_such_unit_anywhere", "--timeout", "1", "-o", str(tmp_path / "x"))
    assert out.returncode == 3, out.stderr
    assert not (tmp_path / "x").exists()


@pytest.mark.ros
def test_live_replay_drives_a_running_unit(tmp_path: Path, processes: Any) -> None:
    """``--live``: the recorded EM reports and operator commands go to a fresh unit node started
    from the bag's own configuration; its transitions match the recording."""
    config = json.loads(
        load(BAGS / "alarm_abort_clear_reset").unit("robot_cell").config_json or "{}"
    )
    cell_file = tmp_path / "cell.yaml"
    cell_file.write_text(config["cell_yaml"])
    processes.module("unit", "packml_ros2.unit_node", str(cell_file), "robot_cell", "--ros-args",
                     "-p", f"persistence_path:={tmp_path / 'store.sqlite3'}")  # fmt: skip
    out = packml(
        "replay", str(BAGS / "alarm_abort_clear_reset"), "--live", "--speed", "2", "--timeout", "20"
    )
    assert out.returncode == 0, out.stdout + out.stderr
    assert "--live at speed 2: match" in out.stdout
    # the unit is no longer fresh (it ran the recording): refused
    again = packml("replay", str(BAGS / "alarm_abort_clear_reset"), "--live", "--timeout", "20")
    assert again.returncode == 3 and "freshly started" in again.stderr  # not a mismatch


def test_live_without_a_unit_is_unavailable() -> None:
    out = packml("replay", str(BAGS / "normal_production"), "--live", "--timeout", "1")
    assert out.returncode == 3 and "not running" in out.stderr


def test_bags_from_other_writers_are_accepted(tmp_path: Path) -> None:
    """independent_writer.mcap is a bare .mcap file of mcap-ros2-support (its own CDR encoder);
    a directory holding it (no metadata.yaml) works too."""
    d = tmp_path / "dir"
    d.mkdir()
    shutil.copy(BAGS / "independent_writer.mcap", d / "x.mcap")
    r = replay(d).assert_matches()
    assert r.digest() == replay(BAGS / "normal_production").digest()


def test_the_readme_replay_example_prints_what_the_readme_shows(tmp_path: Path) -> None:
    """Run verbatim; the README showed other counts than it printed (issue 24) and no test ran it.
    Only the time taken may differ."""
    from test.workspace.tools import ROOT, code_blocks, console_commands, shell

    found = [(command, shown) for block in code_blocks("console")
             for command, shown in console_commands(block)
             if command.startswith("packml replay test/bags/")]  # fmt: skip
    assert found, "the README's replay example was not found"
    for command, shown in found:
        result = shell(command, tmp_path, ROOT)
        assert result.returncode == 0, result.stdout
        timeless = [re.sub(r"\d+(\.\d+)? s\)", "TIME s)", line) for line in (result.stdout, *shown)]
        assert timeless[0].splitlines() == timeless[1:], (command, result.stdout, shown)


# -- issue 27: malformed recordings, each its own reason and exit code ---------------------------------
def _unit_input(raw: bytes, **changes: Any) -> bytes:
    m = deserialize_message(raw, UnitInput)
    for k, v in changes.items():
        setattr(m, k, v)
    return bytes(serialize_message(m))


def test_each_malformed_recording_has_its_own_reason_and_exit_code(tmp_path: Path) -> None:
    src = BAGS / "normal_production"
    inputs = [raw for t, raw in _messages(src) if t.endswith("/input_log")]
    prev = deserialize_message(inputs[6], UnitInput).stamp

    def on_input(i: int) -> Any:
        return lambda t, n, raw: t.endswith("/input_log") and n == i

    earlier = type(prev)(sec=prev.sec - 1, nanosec=prev.nanosec)
    cases: dict[str, tuple[int, str, dict[str, Any]]] = {
        # input #8 stamped before input #7 (the log's indices go on, its stamps go back)
        "stamps_out_of_order": (5, "stamped", {
            "change": lambda t, i, raw: _unit_input(raw, stamp=earlier) if on_input(7)(t, i, raw) else raw}),
        "duplicate_input": (6, "input #8 is in the recording twice", {
            "add": lambda t, i, raw: [raw] if on_input(7)(t, i, raw) else []}),
        "missing_input": (7, "inputs #8..#8 are missing", {"drop": on_input(7)}),
        "restarted": (8, "started more than once", {
            "add": lambda t, i, raw: [inputs[0]] if on_input(len(inputs) - 1)(t, i, raw) else []}),
    }  # fmt: skip
    for reason, (code, text, how) in cases.items():
        dst = tmp_path / reason
        rewrite(src, dst, **how)
        with pytest.raises(RecordingError, match=text) as caught:
            replay(dst)
        assert caught.value.reason == reason and caught.value.exit_code == code
        out = packml("replay", str(dst))
        assert out.returncode == code, (reason, out.returncode, out.stderr)
        assert f"[{reason}]" in out.stderr and text in out.stderr and "Traceback" not in out.stderr
    cut = tmp_path / "cut"
    shutil.copytree(src, cut)
    f = cut / "normal_production.mcap"
    f.write_bytes(f.read_bytes()[: f.stat().st_size * 2 // 3])
    out = packml("replay", str(cut))
    assert out.returncode == 4 and "[unreadable]" in out.stderr, out.stderr


def test_only_a_step_of_the_wall_clock_may_be_stamped_before_the_input_ahead_of_it() -> None:
    """Issue 25 item 6: the engine takes a step of the wall clock as an input stamped with the
    new clock's time; after a step back it is the one record whose stamp goes back."""
    from packml_ros2.bag.replay import check_log

    stepped = [(1, 10.0, "start"), (2, 11.0, "command"), (3, 5.0, "clock.step"), (4, 5.5, "speed")]
    assert check_log(stepped, "u") == [0, 1, 2, 3]
    edited = [(1, 10.0, "start"), (2, 11.0, "command"), (3, 5.0, "speed")]
    with pytest.raises(RecordingError, match=r"stamped 6\.000000 s before") as caught:
        check_log(edited, "u")
    assert caught.value.reason == "stamps_out_of_order"


def _messages(bag: Path) -> list[tuple[str, bytes]]:
    from rosbags.highlevel import AnyReader

    with AnyReader([bag]) as reader:
        return [(c.topic, bytes(d)) for c, _, d in reader.messages()]


# -- issue 27: a line recorded at any age replays, checked to its end ---------------------------------
def _line(publish_period: float = 5.0, cycle: float = 0.25, **defaults: Any) -> tuple[Any, dict[str, Any]]:  # fmt: skip
    from packml_ros2.core import Cmd
    from test.core.line_sim import SimEm, SimLine
    from test.core.test_line_scenarios import D, cell_doc

    doc = cell_doc(publish_period=publish_period)
    doc["defaults"].update(defaults)
    sim = SimLine(doc, [SimEm("filler", "infeed", dict(D), cycle, 10),
                        SimEm("packer", "loader", dict(D), 2 * cycle)])  # fmt: skip
    sim.at(1, lambda: sim.cell_command(Cmd.RESET))
    sim.at(4, lambda: sim.cell_command(Cmd.START))
    return sim, doc


def _faults(sim: Any, begin: float, end: float, every: float = 60.0) -> None:
    """From ``begin`` to ``end`` (sim s), every ``every`` s: a jam on the filler (alarm, Stop,
    Reset, Start) and a blocked packer (the filler suspended)."""
    from packml_ros2.core import Cmd

    t = begin
    while t + 40 < end:
        sim.at(t + 10, lambda: sim.alarm("filler", "infeed", 202, True))
        sim.at(t + 15, lambda: sim.alarm("filler", "infeed", 202, False))
        sim.at(t + 16, lambda: sim.command("filler", Cmd.RESET))
        sim.at(t + 18, lambda: sim.command("filler", Cmd.START))
        sim.at(t + 30, lambda: sim.interlock("packer", "loader", blocked=True))
        sim.at(t + 34, lambda: sim.interlock("packer", "loader", blocked=False))
        t += every


@pytest.fixture(scope="module")
def late_line_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A line that had logged more than 5000 inputs when the recorder joined (its snapshot), then
    ran on with faults for 3 minutes until the recorder stopped."""
    import yaml

    sim, doc = _line()
    _faults(sim, 0, 3000, every=45)
    joined = 0.0
    while sim.line.index <= 5200:
        joined += 100
        sim.run_until(joined)
    assert joined < 3000
    sim.snapshot()
    _faults(sim, joined, joined + 200, every=45)
    sim.run_until(joined + 200)
    bag = tmp_path_factory.mktemp("line") / "late_line"
    sim.write_bag(bag, yaml.safe_dump(doc), joined=joined, stop=joined + 180)
    return bag


@pytest.mark.slow
@pytest.mark.timeout(900)  # (a simulated line of an hour or days: a loaded host)
def test_a_line_recorded_after_more_than_5000_inputs_replays(late_line_bag: Path,
                                                             tmp_path: Path) -> None:  # fmt: skip
    from packml_ros2.bag import line

    [rec] = line.load(late_line_bag)
    assert len(rec.snapshots) == 1 and rec.snapshots[0].index > 5000
    assert rec.inputs[0].index > 1  # the log does not reach the coordinator's start
    [result] = line.check(late_line_bag)
    assert result.ok, result.report()
    assert result.origin == rec.snapshots[0].index
    assert result.compared["episodes"] >= 6 and result.compared["losses"] >= 100, result.compared
    report = tmp_path / "junit.xml"
    out = packml("replay", str(late_line_bag), "--junit", str(report))
    assert out.returncode == 0, out.stdout + out.stderr
    assert f"from a snapshot after input #{result.origin}" in out.stdout
    import xml.etree.ElementTree as ET

    cases = ET.parse(report).getroot().findall(".//testcase")
    assert sorted(c.get("name") for c in cases) == ["line sim episodes", "line sim losses"]
    assert not any(c.find("failure") is not None for c in cases)


@pytest.mark.slow
@pytest.mark.timeout(900)  # (a simulated line of an hour or days: a loaded host)
def test_the_line_topics_are_checked_to_the_end(late_line_bag: Path, tmp_path: Path) -> None:
    """The last line/episodes message (the one that closes an episode) or the last line/losses
    message deleted or altered: a mismatch, named in the JUnit report."""
    import xml.etree.ElementTree as ET

    from packml_interfaces.msg import LineEpisode, LineLosses

    counts = {t.rsplit("/", 1)[1]: n for t, n in _topic_counts(late_line_bag).items()}

    def altered(cls: Any, field: str, value: Any) -> Any:
        def change(raw: bytes) -> bytes:
            m = deserialize_message(raw, cls)
            setattr(m, field, value)
            return bytes(serialize_message(m))

        return change

    last_episode = deserialize_message([r for t, r in _messages(late_line_bag) if t.endswith("/episodes")][-1], LineEpisode)  # fmt: skip
    assert not last_episode.open  # the one that closes an episode
    mutants = {
        "episodes": ("deleted", None),
        "losses": ("deleted", None),
        "episodes ": ("altered", altered(LineEpisode, "reason", "a reason nobody gave")),
        "losses ": ("altered", altered(LineLosses, "window", "2h")),
    }
    for key, (how, change) in mutants.items():
        topic = key.strip()
        last = counts[topic] - 1
        dst = tmp_path / f"{how}_{topic}"
        if change is None:
            rewrite(late_line_bag, dst, drop=lambda t, i, raw, topic=topic, last=last: t.endswith(f"/line/{topic}") and i == last)  # fmt: skip
        else:
            rewrite(late_line_bag, dst, change=lambda t, i, raw, topic=topic, last=last, change=change: change(raw) if t.endswith(f"/line/{topic}") and i == last else raw)  # fmt: skip
        report = tmp_path / f"{how}_{topic}.xml"
        out = packml("replay", str(dst), "--junit", str(report))
        assert out.returncode == 1, (how, topic, out.stdout, out.stderr)
        assert f"line/{topic}" in out.stdout, out.stdout
        failed = [c.get("name") for c in ET.parse(report).getroot().findall(".//testcase") if c.find("failure") is not None]  # fmt: skip
        assert failed == [f"line sim {topic}"], (how, topic, failed)


@pytest.mark.slow
@pytest.mark.timeout(900)  # (a simulated line of an hour or days: a loaded host)
def test_a_line_with_days_of_simulated_time_recorded_late_replays(tmp_path: Path) -> None:
    """Production, then the line stopped over three days, started again and recorded then: the
    replay starts from the snapshot (its lifetime and since-reset windows carry the days) and
    matches to the end."""
    import yaml

    from packml_ros2.core import Cmd

    sim, doc = _line(publish_period=60.0, admin_period=600.0)  # (idle days: few wake-ups)
    days = 3 * 86400
    _faults(sim, 0, 600)
    sim.at(600, lambda: sim.cell_command(Cmd.STOP))
    sim.at(days, lambda: sim.cell_command(Cmd.RESET))
    sim.at(days + 3, lambda: sim.cell_command(Cmd.START))
    _faults(sim, days + 10, days + 300)
    sim.run_until(days + 60)
    sim.snapshot()
    index, _, state = sim.snapshots[-1]
    lifetime = state["line"]["ledger"]["lifetime"]
    line_time = sum(ns for _, _, ns in lifetime[""]["time"])  # the line's ledger: days
    assert line_time >= days * 10**9, line_time
    sim.run_until(days + 300)
    bag = tmp_path / "days"
    sim.write_bag(bag, yaml.safe_dump(doc), joined=days + 60, stop=days + 290)
    out = packml("replay", str(bag))
    assert out.returncode == 0, out.stdout + out.stderr
    assert f"from a snapshot after input #{index}" in out.stdout
    assert re.search(r"line sim: match \(\d+ inputs from a snapshot after input #\d+; ([1-9]\d*) episodes, ([1-9]\d*) losses compared\)", out.stdout), out.stdout  # fmt: skip
