"""Issue 27 (replay speed): ``packml replay`` reads an indexed MCAP file with its own loop over the
decompressed chunks (recording.mcap_messages) instead of rosbags' ``messages()``. It must yield
exactly what rosbags yields, in the same order, and refuse what rosbags refuses."""

from __future__ import annotations

import struct
from pathlib import Path

import pytest
from rosbags.rosbag2.errors import ReaderError
from rosbags.rosbag2.storage_mcap import McapReader

from packml_ros2.bag.recording import RecordingError, load, mcap_messages

# the independent writer of multi-chunk files: a dev requirement (requirements/dev.txt), not a
# dependency of the package (package.xml), so a workspace without it skips these tests
_writer = pytest.importorskip("mcap.writer")
CompressionType, Writer = _writer.CompressionType, _writer.Writer

ROOT = Path(__file__).resolve().parents[2]
BAGS = ROOT / "test" / "bags"
FILES = sorted(BAGS.rglob("*.mcap"))


def _read(file: Path, topics: set[str] | None) -> tuple[list[tuple[str, int, bytes]], ...]:
    """(rosbags' messages, ours) of ``topics`` (None: all) as (topic, time, bytes)."""
    reader = McapReader(file)
    reader.open()
    try:
        conns = [c for c in reader.connections if topics is None or c.topic in topics]
        theirs = [(c.topic, t, bytes(d)) for c, t, d in reader.messages(conns)]
        ours = [(c.topic, t, bytes(d)) for c, t, d in mcap_messages(reader, conns)]
        return theirs, ours
    finally:
        reader.close()


@pytest.mark.parametrize("file", FILES, ids=lambda f: f.name)
def test_the_recorded_bags_read_as_rosbags_reads_them(file: Path) -> None:
    theirs, ours = _read(file, None)
    assert theirs and ours == theirs
    every = len(ours)
    some = {t for t, _, _ in theirs if not t.endswith("/em_reports")}
    theirs, ours = _read(file, some)
    assert theirs and ours == theirs and len(ours) < every


def _multi_chunk(path: Path, compression: CompressionType) -> Path:
    """A ros2-profile MCAP file of small chunks whose messages are out of time order within and
    across chunks, with equal times in different chunks and on different topics."""
    with path.open("wb") as f:
        w = Writer(f, chunk_size=200, compression=compression)
        w.start(profile="ros2", library="test")
        schema = w.register_schema("std_msgs/msg/String", "ros2msg", b"string data")
        ids = [w.register_channel(f"/t{i}", "cdr", schema) for i in range(3)]
        times = [5, 3, 3, 9, 1, 3, 7, 7, 2, 3, 8, 0, 3, 6, 6, 4] * 3
        for n, t in enumerate(times):
            text = f"message {n}".encode() + b"\0"
            data = b"\x00\x01\x00\x00" + struct.pack("<I", len(text)) + text
            w.add_message(ids[n % 3], log_time=t, data=data, publish_time=t, sequence=n)
        w.finish()
    return path


@pytest.mark.parametrize("compression", [CompressionType.NONE, CompressionType.ZSTD])
def test_order_across_chunks_and_equal_times_is_rosbags_order(
    tmp_path: Path, compression: CompressionType
) -> None:
    file = _multi_chunk(tmp_path / "x.mcap", compression)
    reader = McapReader(file)
    reader.open()
    assert len(reader.chunks) > 5
    reader.close()
    theirs, ours = _read(file, None)
    assert len(theirs) == 48 and ours == theirs
    theirs, ours = _read(file, {"/t0", "/t2"})
    assert len(theirs) == 32 and ours == theirs


def test_a_damaged_record_inside_a_chunk_is_refused_as_rosbags_refuses_it(tmp_path: Path) -> None:
    file = _multi_chunk(tmp_path / "x.mcap", CompressionType.NONE)
    data = bytearray(file.read_bytes())
    # the first message record (opcode 5) inside the first chunk: its length made too large
    reader = McapReader(file)
    reader.open()
    chunk = reader.chunks[0]
    reader.close()
    at = chunk.chunk_start_offset + 9 + 40 + len(chunk.compression)
    while data[at] != 0x05:  # the records before it (schema, channel)
        at += 9 + struct.unpack_from("<Q", data, at + 1)[0]
    data[at + 1 : at + 9] = struct.pack("<Q", 10_000)
    file.write_bytes(bytes(data))
    reader = McapReader(file)
    reader.open()
    try:
        with pytest.raises(ReaderError):
            list(reader.messages(reader.connections))
        with pytest.raises(ReaderError):
            mcap_messages(reader, reader.connections)
    finally:
        reader.close()


def test_a_cut_bag_is_still_refused_as_unreadable(tmp_path: Path) -> None:
    src = BAGS / "normal_production" / "normal_production.mcap"
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(src.read_bytes()[: src.stat().st_size // 2])
    with pytest.raises(RecordingError) as err:
        load(cut)
    assert err.value.reason == "unreadable"
