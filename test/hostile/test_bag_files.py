"""Issue 15: a bag is hostile input too. Its YAML (metadata.yaml, the QoS of each topic) is read
by the bounded loader of cell files: a deeply nested or bomb-laden metadata.yaml is a refusal
with a reason, where libyaml's composer crashed `packml replay` (SIGSEGV)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

REPO = Path(__file__).resolve().parents[2]
BAG = REPO / "test" / "bags" / "hold_unhold"
BOMB = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{c}: &{c} [{', '.join([f'*{p}'] * 9)}]\n" for p, c in zip("abcdefgh", "bcdefghi", strict=True)
)

#: packml replay's refusals of a bag: 2 unusable, 4 unreadable (damaged or cut; issue 27 gave
#: each malformed recording its own code). Never 1, "a difference", nor a traceback.
REFUSED = (2, 4)


@pytest.mark.parametrize(
    ("metadata", "reason"),
    [
        ("rosbag2_bagfile_information: " + "[" * 200_000 + "]" * 200_000 + "\n", "nested more"),
        (BOMB + "rosbag2_bagfile_information: *i\n", "alias bomb"),
        ("rosbag2_bagfile_information: {version: 9}\nrosbag2_bagfile_information: {}\n", "twice"),
        ("rosbag2_bagfile_information: [1, 2]\n", "no rosbag2_bagfile_information mapping"),
        ("[1, 2]\n", "no rosbag2_bagfile_information mapping"),
    ],
)
def test_a_hostile_metadata_file_is_refused_with_a_reason(
    tmp_path: Path, metadata: str, reason: str
) -> None:
    bag = tmp_path / "bag"
    shutil.copytree(BAG, bag)
    (bag / "metadata.yaml").write_text(metadata)
    result = subprocess.run([sys.executable, "-m", "packml_ros2.cli.main", "replay", str(bag)],
                            capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
    assert result.returncode in REFUSED, (
        result.returncode,
        result.stderr[-500:],
    )  # was -11 (SIGSEGV)
    assert reason in result.stderr and "Traceback" not in result.stderr, result.stderr[-500:]
    assert len(result.stderr) < 2000


# -- issue 25 item 8: bags whose contents no recorder writes ------------------------------------------
CELL_FILE = REPO / "test" / "bags" / "cell.yaml"
MAX_SECONDS = 30
MAX_RSS_MB = 600  # the replay process's peak (a clean replay of these bags: ~150 MB)


def replay_cli(bag: Path) -> subprocess.CompletedProcess[str]:
    """``packml replay`` as a user runs it, its peak memory bounded from outside (ulimit -v)."""
    import resource

    def limit() -> None:
        cap = 4 * 1024**3  # address space: a runaway allocation fails instead of eating the machine
        resource.setrlimit(resource.RLIMIT_AS, (cap, cap))

    return subprocess.run([sys.executable, "-m", "packml_ros2.cli.main", "replay", str(bag)],
                          capture_output=True, text=True, timeout=MAX_SECONDS, check=False,
                          preexec_fn=limit)  # fmt: skip


def synthetic(tmp_path: Path, name: str, tamper: Any = None) -> Path:
    """A small recording of the reference unit (reset, start, a few cycles), ``tamper(sim)``
    applied to its messages before it is written."""
    from packml_interfaces.msg import EmReport

    from packml_ros2.bag.synthetic import SyntheticUnit
    from packml_ros2.core import Cmd, load_cell

    config = load_cell(CELL_FILE).units["robot_cell"]
    sim = SyntheticUnit(config, CELL_FILE.read_text())
    for em in config.equipment_modules:
        sim.report(0.01, em.name, EmReport.KIND_HEARTBEAT)
    sim.call(0.5, sim.unit.command, Cmd.RESET)
    sim.advance(2.0)
    if tamper is not None:
        tamper(sim)
    sim.write(tmp_path / name, stop=3.0)
    return tmp_path / name


def _input(sim: Any, index: int, name: str, args_json: str, t: float | None = None) -> bytes:
    from rclpy.serialization import serialize_message

    from packml_ros2 import convert
    from packml_ros2.bag.topics import UNIT_TOPICS, msg_class

    msg = msg_class(UNIT_TOPICS["input_log"])(
        stamp=convert.stamp(sim.now if t is None else t), index=index, unit="robot_cell",
        name=name, args_json=args_json)  # fmt: skip
    return bytes(serialize_message(msg))


def deep_json(sim: Any) -> None:
    log = sim.messages["input_log"]
    t, _ = log[-1]
    log[-1] = (t, _input(sim, len(log), "ack_alarms", '{"a":' + "[" * 100_000 + "]" * 100_000 + "}", t))  # fmt: skip


def nan_start(sim: Any) -> None:
    import json

    from rclpy.serialization import deserialize_message

    from packml_ros2.bag.topics import UNIT_TOPICS, msg_class

    t, raw = sim.messages["input_log"][0]
    m = deserialize_message(raw, msg_class(UNIT_TOPICS["input_log"]))
    args = json.loads(m.args_json)
    args["time"] = float("nan")
    sim.messages["input_log"][0] = (t, _input(sim, 1, "start", json.dumps(args), t))


def config_of(data: str) -> Any:
    def tamper(sim: Any) -> None:
        from rclpy.serialization import serialize_message

        from packml_ros2.bag.topics import UNIT_TOPICS, msg_class

        sim.messages["config"].append((sim.start, bytes(serialize_message(msg_class(UNIT_TOPICS["config"])(data=data)))))  # fmt: skip

    return tamper


def garbage_config(sim: Any) -> None:
    sim.messages["config"].append((sim.start, b"\x00\x01\x00\x00" + b"\xff" * 3))


def garbage_input(sim: Any) -> None:
    sim.messages["input_log"].append((sim.now, b"\x00\x00\x00\x00" + b"\xff\xff\xff\x7f" * 4))


def years_ahead(sim: Any) -> None:
    from rclpy.serialization import deserialize_message, serialize_message

    from packml_ros2.bag.topics import UNIT_TOPICS, msg_class

    t, raw = sim.messages["status"][-1]
    m = deserialize_message(raw, msg_class(UNIT_TOPICS["status"]))
    m.stamp.sec += 10 * 365 * 86400
    sim.messages["status"].append((t, bytes(serialize_message(m))))


@pytest.mark.parametrize(
    ("tamper", "reason"),
    [
        (deep_json, "nested 100001 levels deep"),
        (nan_start, "holds NaN, not a number"),
        (config_of("not json {"), "the configuration of /demo_cell/robot_cell is not JSON"),
        (config_of("[1, 2]"), "the configuration of /demo_cell/robot_cell is not a JSON object"),
        (garbage_config, "cannot read the bag"),
        (garbage_input, "cannot read the bag"),
        (years_ahead, "is stamped +315360000 s from its last message"),
    ],
    ids=[
        "deep-json",
        "nan-start",
        "config-not-json",
        "config-array",
        "cdr-config",
        "cdr-input",
        "10-years-ahead",
    ],
)
def test_a_bag_no_recorder_writes_is_one_line_exit_2_in_bounded_time(
    tmp_path: Path, tamper: Any, reason: str
) -> None:
    """Issue 25 item 8: each of these ended in a traceback with exit 1 (the code for "a
    difference"), or ran on (a status dated 10 years ahead: 980 MB after 30 s, growing)."""
    bag = synthetic(tmp_path, "bag", tamper)
    result = replay_cli(bag)
    assert result.returncode in REFUSED, (result.returncode, result.stderr[-1500:])
    assert "Traceback" not in result.stderr and reason in result.stderr, result.stderr[-1500:]
    assert len(result.stderr.strip().splitlines()) == 1 and len(result.stderr) < 2000, result.stderr


def test_the_untampered_bag_replays(tmp_path: Path) -> None:
    result = replay_cli(synthetic(tmp_path, "bag"))
    assert result.returncode == 0, result.stderr[-1500:]


def test_a_damaged_size_in_an_mcap_record_is_a_refusal(tmp_path: Path) -> None:
    """A record length read from a damaged file (2**62 bytes) raised MemoryError."""
    import struct

    bag = tmp_path / "bag"
    shutil.copytree(BAG, bag)
    mcap = bag / "hold_unhold.mcap"
    data = bytearray(mcap.read_bytes())
    summary_start = struct.unpack_from("<Q", data, len(data) - 8 - 8 - 4 - 8 - 8)[0]  # the footer
    assert 0 < summary_start < len(data)
    struct.pack_into("<Q", data, summary_start + 1, 2**62)  # the first summary record's length
    mcap.write_bytes(bytes(data))
    result = replay_cli(bag)
    assert result.returncode in REFUSED and "Traceback" not in result.stderr, result.stderr[-1500:]
    assert "cannot read the bag" in result.stderr, result.stderr[-1500:]


def test_a_chunk_that_expands_beyond_what_it_declares_is_refused_in_bounded_memory() -> None:
    """A zstd bomb: 2 GB of zeros in a frame of tens of kB. rosbags decompressed a chunk whole
    (a 64 kB bag expanded to 1.85 GB); now a chunk decompresses up to the size it declares, and
    declares at most MAX_CHUNK_BYTES."""
    import resource

    from rosbags.rosbag2 import storage_mcap
    from rosbags.rosbag2.errors import ReaderError

    from packml_ros2.bag.recording import MAX_CHUNK_BYTES, _bound_decompression

    _bound_decompression()
    zstd: Any = storage_mcap.zstd
    packer = zstd.ZstdCompressor()
    zeros = bytes(16 * 1024 * 1024)
    bomb = b"".join(packer.compress(zeros) for _ in range(128)) + packer.flush()
    assert len(bomb) < 200_000
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    for declared in (1024 * 1024, 2**31, MAX_CHUNK_BYTES + 1):
        with pytest.raises(ReaderError):
            storage_mcap.decompress(bomb, "zstd", declared, 0)
    grown_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024
    assert grown_mb < 100, f"peak RSS grew {grown_mb:.0f} MB"
    packer2 = zstd.ZstdCompressor()
    small = packer2.compress(b"abc" * 1000) + packer2.flush()
    assert storage_mcap.decompress(small, "zstd", 3000, 0) == b"abc" * 1000


def test_a_fifo_is_not_a_bag(tmp_path: Path) -> None:
    """A FIFO as the bag (or in it) hung ``packml replay`` in open()."""
    import os

    fifo = tmp_path / "bag.mcap"
    os.mkfifo(fifo)
    result = replay_cli(fifo)
    assert result.returncode == 2 and "not a regular file (a named pipe (FIFO))" in result.stderr, result.stderr  # fmt: skip
    bag = tmp_path / "bag"
    shutil.copytree(BAG, bag)
    (bag / "hold_unhold.mcap").unlink()
    os.mkfifo(bag / "hold_unhold.mcap")
    result = replay_cli(bag)
    assert result.returncode == 2 and "not a regular file (a named pipe (FIFO))" in result.stderr, result.stderr  # fmt: skip
