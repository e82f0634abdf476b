"""Reading a PackML bag: per unit its input log, configuration, EM reports and recorded outputs.

Any rosbag2 bag with the unit topics works: ours (rosbags), ``ros2 bag record``'s, or one written
by another writer (e.g. the ``mcap`` / ``mcap-ros2-support`` packages) — a bag directory with
metadata.yaml, a directory holding one ``.mcap`` / ``.db3`` file, or such a file. Messages are
read with rosbags (it uses the definitions stored in the bag); the stored definition of every
packml type must equal the installed one (same RIHS01 hash), since values are compared with the
installed types.

A bag is hostile input like a cell file (:func:`load` refuses it with one
:class:`RecordingError` line, which ``packml replay`` reports with exit code 2): a path that is not
a regular file or directory (a FIFO would block), sizes and nesting that do not fit
(:data:`MAX_CHUNK_BYTES` decompressed per chunk, however the chunk declares itself: a "zstd bomb"
of 64 kB once expanded to 1.85 GB; :data:`MAX_MESSAGE_BYTES` of messages in all; damaged sizes
that ask for more memory than there is), messages that do not decode, notes and configurations
that are not what the recorder writes (a JSON object, finite numbers), and times no recording
holds: a stamp more than :data:`MAX_SKEW` away from the span the bag was recorded in (one message
dated 10 years ahead made the replay run through 10 years of deadlines).
"""

from __future__ import annotations

import functools
import json
import math
import os
import sqlite3
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rclpy.serialization import deserialize_message

from ..core.files import kind_of
from .cdr import raw_stamp, read_unit_input
from .topics import (
    CUSTOM_KEY,
    OUTPUT_TOPICS,
    UNIT_TOPICS,
    installed_hash,
    msg_class,
    split_topic,
    typestore,
)
from .upgrade import Upgrade, definition_store, upgrade_for

#: Why a recording cannot be replayed (:attr:`RecordingError.reason`) -> the exit code of
#: ``packml replay``: a CI job tells a damaged file from an incomplete or inconsistent log.
REASONS: dict[str, int] = {
    "unusable": 2,  # not a PackML recording, no configuration, another version's, ...
    "unreadable": 4,  # the file is cut short or damaged
    "stamps_out_of_order": 5,  # an input log whose stamps go back while its indices go on
    "duplicate_input": 6,  # an input log index recorded twice with different contents
    "missing_input": 7,  # inputs missing: a gap, or no start and no snapshot to begin from
    "restarted": 8,  # the unit (coordinator) started again during the recording
}


class RecordingError(Exception):
    """The bag cannot be replayed (the message says why and what to do; :attr:`reason`: a code
    of :data:`REASONS`)."""

    def __init__(self, message: str, reason: str = "unusable") -> None:
        super().__init__(message)
        self.reason = reason if reason in REASONS else "unusable"

    @property
    def exit_code(self) -> int:
        return REASONS[self.reason]


#: A bag without our recorder's stop time: outputs are compared up to its last message less this
#: (seconds: a deadline's output goes out at the node's next 50 ms tick, then travels), and at
#: least up to the unit's last input in the bag (a unit publishes what happened up to an input
#: before that input's record).
FOREIGN_MARGIN = 0.1
#: bytes one chunk of a bag may decompress to (rosbag2 writes chunks of about 1 MB)
MAX_CHUNK_BYTES = 256 * 1024 * 1024
#: bytes of messages one bag may hold (what a replay keeps in memory)
MAX_MESSAGE_BYTES = 1024 * 1024 * 1024
#: s: how far a unit's stamp may lie outside the span of the bag's receive times (clocks of hosts)
MAX_SKEW = 3600.0
#: how deeply the JSON of a bag (notes, configurations, inputs) may nest
MAX_JSON_DEPTH = 64


@dataclass
class Input:
    index: int
    time: float
    name: str
    args_json: str

    @property
    def args(self) -> dict[str, Any]:
        value: dict[str, Any] = json.loads(self.args_json)
        return value


@dataclass
class Snapshot:
    """A unit's engine state as the recorder received it (``<unit>/snapshot``): replay can start
    from it, applying the inputs after ``index``."""

    index: int
    time: float
    state_json: str


@dataclass
class UnitRecording:
    """One unit's part of a bag."""

    prefix: str  # /<cell>/<unit>
    inputs: list[Input] = field(default_factory=list)
    #: output topic -> recorded messages (raw CDR), in the order received; only topics in the bag
    outputs: dict[str, list[bytes]] = field(default_factory=dict)
    #: output topic -> DDS publication sequence number of each recorded message (our recorder)
    publications: dict[str, list[int]] = field(default_factory=dict)
    config_json: str | None = None
    em_reports: list[tuple[int, bytes]] = field(default_factory=list)  # (bag time ns, raw)
    snapshots: list[Snapshot] = field(default_factory=list)
    #: topic -> how its messages, recorded with an older definition, were carried into the
    #: installed type (replay compares only the fields they had: bag/upgrade.py)
    upgrades: dict[str, Upgrade] = field(default_factory=dict)

    @property
    def name(self) -> str:
        if self.config_json:
            name = json.loads(self.config_json).get("unit")
            if name:
                return str(name)
        return self.prefix.rsplit("/", 1)[-1]

    @property
    def cell(self) -> str:
        return self.prefix.rsplit("/", 1)[0].strip("/")


@dataclass
class Recording:
    path: Path
    storage: str
    units: dict[str, UnitRecording]  # by prefix
    custom: dict[str, Any]
    message_count: int
    #: every connection: (topic, msgtype, msgdef text, digest, offered QoS, bag messages)
    connections: list[Any]
    raw_messages: list[tuple[Any, int, bytes]] = field(default_factory=list)
    digests: dict[str, str] = field(default_factory=dict)  # msgtype -> stored RIHS01
    #: the bag's last message (receive time, seconds); None: no message
    end: float | None = None
    #: the bag's first message (receive time, seconds); None: no message
    start: float | None = None

    @property
    def stop(self) -> float | None:
        """When our recorder stopped (seconds; the units' clock on one host); None: the bag does
        not say (another recorder's)."""
        stopped = self.custom.get("stopped_at_ns")
        if (
            isinstance(stopped, (int, float))
            and not isinstance(stopped, bool)
            and math.isfinite(stopped)
        ):
            return float(stopped) * 1e-9
        return None

    def unit(self, name: str) -> UnitRecording:
        for u in self.units.values():
            if name in (u.prefix, u.name, u.prefix.strip("/")):
                return u
        raise KeyError(f"no unit {name!r} in {self.path} (units: {', '.join(self.units)})")


def bag_path(path: str | Path) -> Path:
    """What rosbags opens: a bag directory (metadata.yaml), else its single storage file."""
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{p}: no such bag")
    if p.is_dir() and not (p / "metadata.yaml").exists():
        files = sorted([*p.glob("*.mcap"), *p.glob("*.db3")])
        if len(files) != 1:
            raise RecordingError(
                f"{p}: neither a rosbag2 bag (no metadata.yaml) nor a directory with one .mcap/.db3 file"
            )
        p = files[0]
    for f in [p, *(x for x in p.iterdir() if x.name != "metadata.yaml")] if p.is_dir() else [p]:
        kind = kind_of(os.stat(f).st_mode)
        if kind and not (f is p and kind == "a directory"):
            raise RecordingError(f"{f}: not a regular file ({kind}): not a bag")
    return p


def load(path: str | Path, keep_raw: bool = False, em_reports: bool = True) -> Recording:
    """Read the bag at ``path``. ``keep_raw``: also keep every message (for ``--update``);
    ``em_reports=False`` leaves the EM reports unread: the offline check does not need them (the
    input log holds every report the unit applied), only ``--live`` publishes them."""
    p = bag_path(path)
    _bound_decompression()
    try:
        with _open(p) as bag:
            recording = _load(bag, path, keep_raw, em_reports)
    except RecordingError:
        raise
    except MemoryError:
        raise RecordingError(
            f"{path}: cannot read the bag: a size recorded in it is larger than "
            "this machine's memory (a damaged record?)",
            "unreadable",
        ) from None
    except RecursionError:
        raise RecordingError(
            f"{path}: cannot read the bag: its data is nested too deeply"
        ) from None
    except (
        OSError,
        ValueError,
        KeyError,
        TypeError,
        OverflowError,
        IndexError,
        AttributeError,
        struct.error,
        EOFError,
        RuntimeError,
    ) as exc:
        raise RecordingError(f"{path}: cannot read the bag: {_said(exc)}", "unreadable") from None
    except Exception as exc:  # rosbags' reader errors
        if type(exc).__module__.startswith("rosbags"):
            raise RecordingError(
                f"{path}: cannot read the bag: {_said(exc)}", "unreadable"
            ) from None
        raise
    check(recording, path)
    return recording


def _said(exc: BaseException) -> str:
    """An exception as one short line of a refusal."""
    from ..core.limits import printable

    return printable(str(exc) or type(exc).__name__, 200)


def bounded_json(text: str, what: str) -> Any:
    """``text`` parsed as JSON, if it is JSON nested at most :data:`MAX_JSON_DEPTH` deep with
    finite numbers (else :class:`ValueError` saying what ``what`` is not)."""
    depth = deepest = 0
    quoted = escaped = False
    brackets = text.count("[") + text.count("{")
    for c in (
        text if brackets > MAX_JSON_DEPTH else ""
    ):  # (json.loads recurses: 100 000 brackets are a RecursionError)
        if quoted:
            escaped, quoted = (False, True) if escaped else (c == "\\", c != '"')
        elif c == '"':
            quoted = True
        elif c in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif c in "]}":
            depth -= 1
    if deepest > MAX_JSON_DEPTH:
        raise ValueError(f"{what} is nested {deepest} levels deep (at most {MAX_JSON_DEPTH})")

    def refuse(name: str) -> Any:
        raise ValueError(f"{what} holds {name}, not a number")

    try:
        return json.loads(text, parse_constant=refuse)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{what} is not JSON ({exc.msg} at {exc.pos})") from None


def check(recording: Recording, path: str | Path) -> None:
    """Refuse (:class:`RecordingError`) a bag whose units' configurations are not JSON objects
    or whose stamps lie outside the span it was recorded in (see the module docstring)."""
    if recording.end is None:
        return
    first = recording.start if recording.start is not None else recording.end
    lo, hi = first - MAX_SKEW, recording.end + MAX_SKEW
    stop = recording.custom.get("stopped_at_ns")
    # (the stop bounds a unit's replay, whose engine runs to it; a line-only bag's receive times
    # need not be a clock's: its line is checked on its own messages' numbers)
    units_recorded = any(u.inputs or any(u.outputs.values()) for u in recording.units.values())
    if (
        stop is not None
        and units_recorded
        and (
            not isinstance(stop, int | float)
            or isinstance(stop, bool)
            or not lo <= stop * 1e-9 <= hi
        )
    ):
        raise RecordingError(
            f"{path}: its recorder's stop time {str(stop)[:40]} lies outside the "
            "time the bag was recorded in"
        )
    for unit in recording.units.values():
        if unit.config_json is not None:
            try:
                config = bounded_json(unit.config_json, f"the configuration of {unit.prefix}")
            except ValueError as exc:
                raise RecordingError(f"{path}: {exc}") from None
            if not isinstance(config, dict):
                raise RecordingError(
                    f"{path}: the configuration of {unit.prefix} is not a JSON object"
                )
        stamps = [(f"input #{i.index}", i.time) for i in unit.inputs]
        stamps += [
            (f"{t} message {k}", raw_stamp(m))
            for t, msgs in unit.outputs.items()
            for k, m in enumerate(msgs)
        ]
        for what, t in stamps:
            if not lo <= t <= hi:  # (NaN too)
                shown = (
                    "not a time"
                    if math.isnan(t)
                    else f"{t - recording.end:+.0f} s from its last message"
                )
                raise RecordingError(
                    f"{path}: {unit.prefix} {what} is stamped {shown}: outside the "
                    f"time the bag was recorded in (+-{MAX_SKEW:g} s; a damaged "
                    "bag, or a clock that jumped)"
                )
        for i in unit.inputs:
            if i.args_json.count("[") + i.args_json.count("{") > MAX_JSON_DEPTH:  # (cheap first)
                try:  # (replay parses each input's arguments: json.loads recurses)
                    bounded_json(i.args_json, f"{unit.prefix} input #{i.index}")
                except ValueError as exc:
                    raise RecordingError(f"{path}: {exc}") from None
            if i.name == "start":
                try:
                    args = bounded_json(i.args_json, f"{unit.prefix} input #{i.index}")
                except ValueError as exc:
                    raise RecordingError(f"{path}: {exc}") from None
                started = args.get("time", i.time) if isinstance(args, dict) else None
                if not isinstance(started, int | float) or not lo <= started <= hi:
                    raise RecordingError(
                        f"{path}: {unit.prefix} input #{i.index} (start) has no "
                        "time inside the time the bag was recorded in"
                    )


@functools.cache
def _bound_decompression() -> None:
    """Make rosbags' MCAP reader decompress a chunk only up to the size the chunk declares, and
    only a declared size up to :data:`MAX_CHUNK_BYTES` (its decompressors take no bound: a
    zstd frame that expands to gigabytes was expanded whole). Once per process."""
    from rosbags.rosbag2 import storage_mcap
    from rosbags.rosbag2.errors import ReaderError

    zstd: Any = getattr(storage_mcap, "zstd")  # noqa: B009  (not in its __all__)
    from lz4.frame import LZ4FrameDecompressor

    def bounded(make: Any) -> Any:
        def decompress(data: bytes, size: int) -> bytes:
            if not 0 <= size <= MAX_CHUNK_BYTES:
                raise ReaderError(
                    f"a chunk declares {size} bytes once decompressed (at most {MAX_CHUNK_BYTES})"
                )
            out = bytearray()
            rest = bytes(data)
            while rest and len(out) <= size:
                d = make()
                out += d.decompress(rest, max_length=size + 1 - len(out))
                if not d.eof:
                    break  # (more than declared, or a truncated frame: the size check says so)
                rest = d.unused_data
            if len(out) > size or rest:
                raise ReaderError(f"a chunk expands to more than the {size} bytes it declares")
            return bytes(out)

        return decompress

    storage_mcap.DECOMPRESSORS["zstd"] = bounded(zstd.ZstdDecompressor)
    storage_mcap.DECOMPRESSORS["lz4"] = bounded(LZ4FrameDecompressor)


class _Bag:
    """A bag opened for reading: its storage (rosbags), connections and our notes."""

    def __init__(self, p: Path) -> None:
        self.path = p
        self.storage = "mcap"
        self.custom: dict[str, Any] = {}
        self.reader: Any = None  # a rosbags storage reader, or an AnyReader (general case)
        self.any = False

    def __enter__(self) -> _Bag:
        return self

    def __exit__(self, *_: object) -> None:
        if self.reader is not None:
            self.reader.close()

    @property
    def connections(self) -> list[Any]:
        return list(self.reader.connections)

    def messages(self, connections: Any) -> Any:
        if self.any:
            return self.reader.messages(connections)
        if getattr(self.reader, "chunks", None) and hasattr(self.reader, "bio"):
            return mcap_messages(self.reader, connections or self.reader.connections)
        return self.reader.messages(connections or self.reader.connections)

    def stored_hash(self, conn: Any) -> str | None:
        """RIHS01 of the definition stored for ``conn`` (None: none stored)."""
        if self.any:
            try:
                return str(self.reader.typestore.hash_rihs01(conn.msgtype))
            except Exception:
                return None
        if conn.digest:
            return str(conn.digest)
        fmt = getattr(conn.msgdef.format, "name", "NONE")
        if fmt == "NONE" or not conn.msgdef.data:
            return None
        return _definition_hash(conn.msgtype, fmt, conn.msgdef.data)


def _open(p: Path) -> _Bag:
    """Open a bag: its single storage file directly when that is all there is (fast: no YAML
    parsing by rosbags, no definition parsing per open), otherwise rosbags' AnyReader."""
    from rosbags.rosbag2.storage_mcap import McapReader

    from ..core.safe_yaml import read_document

    bag = _Bag(p)
    file = p
    if p.is_dir():
        # bounded and never recursive on hostile nesting (libyaml's composer crashes the process)
        try:
            document = read_document(p / "metadata.yaml")
        except ValueError as exc:  # (not a damaged storage file: "unusable", not "unreadable")
            raise RecordingError(f"{p}: cannot read the bag: {exc}") from None
        info = document.get("rosbag2_bagfile_information") if isinstance(document, dict) else None
        if not isinstance(info, dict):
            raise RecordingError(
                f"{p}: cannot read the bag: metadata.yaml has no rosbag2_bagfile_information mapping"
            )
        bag.storage = str(info.get("storage_identifier", "mcap"))
        notes = (info.get("custom_data") or {}).get(CUSTOM_KEY)
        if notes:
            try:
                custom = bounded_json(str(notes), "the recorder's notes")
            except ValueError:
                custom = {}
            bag.custom = custom if isinstance(custom, dict) else {}
        files = info.get("relative_file_paths") or []
        simple = (
            len(files) == 1
            and not (info.get("compression_mode") or "").strip()
            and int(info.get("version", 9)) <= 9
            and bag.storage in ("mcap", "sqlite3")
        )
        if not simple:
            return _open_any(bag, p)
        file = p / Path(files[0]).name
    elif p.suffix == ".db3":
        bag.storage = "sqlite3"
    if bag.storage == "sqlite3":
        try:
            bag.reader = _Sqlite(file)
        except (sqlite3.Error, KeyError, ValueError):
            return _open_any(bag, p)
        return bag
    reader = McapReader(file)
    reader.open()
    bag.reader = reader
    return bag


_MESSAGE_HEAD = struct.Struct("<HIQ")  # channel id, sequence, log time (then publish time)
_RECORD_HEAD = struct.Struct("<BQ")  # opcode, length
_U32 = struct.Struct("<I")


def mcap_messages(reader: Any, connections: Any) -> list[tuple[Any, int, memoryview]]:
    """The messages of ``connections`` in an indexed MCAP file opened by rosbags' ``McapReader``,
    in the order its ``messages()`` yields them (by log time; ties: by chunk, then in file
    order), with the same checks (chunk sizes and CRC, bounded decompression, messages outside
    their chunk's declared time span left out) — 5-10x faster: records of other channels (the
    EM reports, most of a recording) are skipped by their length alone, and a wanted message is a
    slice of its decompressed chunk, not a record read through a ``BytesIO``."""
    from rosbags.rosbag2.errors import ReaderError
    from rosbags.rosbag2.storage_mcap import decompress

    channels = {c.id: c for c in connections}
    bio = reader.bio
    found: list[tuple[int, int, int, Any, memoryview]] = []
    order = 0
    for chunk in reader.chunks:
        if not any(chunk.channel_count.get(cid, 0) for cid in channels):
            continue
        start, stop = chunk.message_start_time, chunk.message_end_time + 1
        bio.seek(chunk.chunk_start_offset + 9 + 24)
        head = bio.read(4)
        bio.seek(chunk.chunk_start_offset + 9 + 40 + len(chunk.compression))
        data = bio.read(chunk.compressed_size)
        if len(head) != 4 or len(data) != chunk.compressed_size:
            raise ReaderError(f"Truncated chunk at offset {chunk.chunk_start_offset}.")
        raw = decompress(data, chunk.compression, chunk.uncompressed_size, _U32.unpack(head)[0])
        view = memoryview(raw)
        size = len(raw)
        p = 0
        unpack_record, unpack_message = _RECORD_HEAD.unpack_from, _MESSAGE_HEAD.unpack_from
        offset = chunk.chunk_start_offset
        while p < size:
            if p + 9 > size:
                raise ReaderError(f"Truncated record in the chunk at offset {offset}.")
            op, length = unpack_record(raw, p)
            p += 9
            end = p + length
            if end > size:
                raise ReaderError(f"Truncated record in the chunk at offset {offset}.")
            if op == 0x05:
                if length < 22:
                    raise ReaderError(f"A message record of {length} bytes at offset {offset}.")
                cid, _, log_time = unpack_message(raw, p)
                conn = channels.get(cid)
                if conn is not None and start <= log_time < stop:
                    found.append((log_time, offset, order, conn, view[p + 22 : end]))
                    order += 1
            p = end
    found.sort(key=lambda m: (m[0], m[1], m[2]))
    return [(conn, ts, data) for ts, _, _, conn, data in found]


class _Sqlite:
    """rosbag2's sqlite3 storage (schema 4 and later, i.e. with stored definitions), read with
    the sqlite3 module; rosbags' reader parses every QoS string with a pure-Python YAML parser,
    which costs more than the whole replay of a small bag."""

    def __init__(self, file: Path) -> None:
        from rosbags.interfaces import (
            Connection,
            ConnectionExtRosbag2,
            MessageDefinition,
            MessageDefinitionFormat,
        )
        from rosbags.rosbag2.metadata import parse_qos

        from ..core.safe_yaml import parse_document

        self.db = sqlite3.connect(f"file:{file}?immutable=1", uri=True)
        try:
            (schema,) = self.db.execute("SELECT schema_version FROM schema").fetchone()
            if int(schema) < 4:
                raise ValueError("old schema")
            formats = {
                "ros2msg": MessageDefinitionFormat.MSG,
                "ros2idl": MessageDefinitionFormat.IDL,
            }
            defs = {
                name: MessageDefinition(formats[enc], text)
                for name, enc, text in self.db.execute(
                    "SELECT topic_type, encoding, encoded_message_definition FROM message_definitions"
                )
                if enc in formats
            }
            none = MessageDefinition(MessageDefinitionFormat.NONE, "")
            rows = self.db.execute(
                "SELECT topics.id, name, type, count(messages.id), serialization_format, "
                "offered_qos_profiles, type_description_hash FROM topics LEFT JOIN messages ON "
                "topics.id == messages.topic_id GROUP BY topics.id ORDER BY topics.id"
            ).fetchall()
            self.connections = [
                Connection(
                    cid,
                    topic,
                    msgtype,
                    defs.get(msgtype, none),
                    digest or "",
                    count,
                    ConnectionExtRosbag2(
                        fmt, parse_qos(parse_document(qos or "[]", f"{file}: {topic}") or [])
                    ),
                    self,
                )
                for cid, topic, msgtype, count, fmt, qos, digest in rows
            ]
        except Exception:
            self.db.close()
            raise

    def messages(self, connections: Any) -> Any:
        by_id = {c.id: c for c in connections}
        marks = ",".join("?" for _ in by_id)
        query = (
            f"SELECT topic_id, timestamp, data FROM messages WHERE topic_id IN ({marks}) "
            "ORDER BY timestamp, id"
        )
        for cid, ts, data in self.db.execute(query, tuple(by_id)):
            yield by_id[cid], ts, data

    def close(self) -> None:
        self.db.close()


def _open_any(bag: _Bag, p: Path) -> _Bag:
    from rosbags.highlevel import AnyReader

    reader = AnyReader([p], default_typestore=typestore())
    reader.open()
    bag.reader = reader
    bag.any = True
    return bag


def _upgrade(bag: _Bag, conn: Any) -> Upgrade | None:
    """How ``conn``'s messages, recorded with an older definition, become the installed type."""
    if bag.any:
        store = bag.reader.typestore
    else:
        fmt = getattr(conn.msgdef.format, "name", "NONE")
        if fmt == "NONE" or not conn.msgdef.data:
            return None
        try:
            store = definition_store(conn.msgtype, fmt, conn.msgdef.data)
        except Exception:  # (a definition rosbags cannot parse: no upgrade)
            return None
    return upgrade_for(store, conn.msgtype)


@functools.cache
def _definition_hash(msgtype: str, fmt: str, data: str) -> str:
    return str(definition_store(msgtype, fmt, data).hash_rihs01(msgtype))


def _load(bag: _Bag, path: str | Path, keep_raw: bool, em_reports: bool = True) -> Recording:
    units: dict[str, UnitRecording] = {}
    upgrades: dict[str, Callable[[bytes], bytes]] = {}  # topic -> recorded CDR to installed
    wanted = []
    digests: dict[str, str] = {}
    for conn in bag.connections:
        have = bag.stored_hash(conn)
        if have:
            digests[conn.msgtype] = have
        split = split_topic(conn.topic)
        if split is None or UNIT_TOPICS[split[1]] != conn.msgtype:
            continue
        units.setdefault(split[0], UnitRecording(split[0]))
        if have is not None and have != installed_hash(conn.msgtype):
            upgrade = _upgrade(bag, conn)
            if upgrade is None:
                raise RecordingError(
                    f"{path}: {conn.msgtype} in the bag ({have}) differs from the installed "
                    f"definition ({installed_hash(conn.msgtype)}) other than by fields added "
                    "since: the bag was recorded with another version of packml_interfaces; "
                    "re-record it, or replay it with that version"
                )
            units[split[0]].upgrades[split[1]] = upgrade
            upgrades[conn.topic] = upgrade.convert
        if split[1] in OUTPUT_TOPICS:
            units[split[0]].outputs.setdefault(split[1], [])
        if em_reports or split[1] != "em_reports":
            wanted.append(conn)
    string_cls = msg_class("std_msgs/msg/String")
    input_cls = msg_class("packml_interfaces/msg/UnitInput")
    snapshot_cls = msg_class(UNIT_TOPICS["snapshot"])
    raw_messages: list[tuple[Any, int, bytes]] = []
    count = 0
    last = -1
    first = -1
    held = 0
    by_topic = {c.topic: split_topic(c.topic) for c in wanted}
    for conn, ts, data in bag.messages(() if keep_raw else wanted):
        count += 1
        last = max(last, ts)
        first = ts if first < 0 else min(first, ts)
        raw = bytes(data)
        held += len(raw)
        if held > MAX_MESSAGE_BYTES:
            raise RecordingError(
                f"{path}: its messages hold more than {MAX_MESSAGE_BYTES} bytes: "
                "larger than a bag packml replay reads"
            )
        if keep_raw:
            raw_messages.append((conn, ts, raw))
        split = by_topic.get(conn.topic)
        if split is None:
            continue
        if conn.topic in upgrades:
            try:
                raw = upgrades[conn.topic](raw)
            except Exception as exc:  # rosbags raises several types for bytes it cannot read
                raise RecordingError(
                    f"{path}: a {conn.msgtype} message on {conn.topic} cannot be read by its "
                    f"recorded definition ({type(exc).__name__})"
                ) from None
        unit = units[split[0]]
        name = split[1]
        if name == "input_log":
            fast = read_unit_input(raw)
            if fast is not None:
                sec, nanosec, index, _, input_name, args_json = fast
                unit.inputs.append(Input(index, sec + nanosec * 1e-9, input_name, args_json))
            else:
                m = deserialize_message(raw, input_cls)
                unit.inputs.append(
                    Input(m.index, m.stamp.sec + m.stamp.nanosec * 1e-9, m.name, m.args_json)
                )
        elif name == "config":
            unit.config_json = deserialize_message(raw, string_cls).data
        elif name == "em_reports":
            unit.em_reports.append((ts, raw))
        elif name == "snapshot":
            m = deserialize_message(raw, snapshot_cls)
            unit.snapshots.append(
                Snapshot(m.index, m.stamp.sec + m.stamp.nanosec * 1e-9, m.state_json)
            )
        elif name in unit.outputs:  # (the recipe orders and the stack light are not compared)
            unit.outputs[name].append(raw)
    if not keep_raw:
        count += sum(c.msgcount for c in bag.connections if c not in wanted)
    pubs = bag.custom.get("publications", {})
    for unit in units.values():
        for topic, recorded in unit.outputs.items():
            ranges = pubs.get(f"{unit.prefix}/{topic}")
            if ranges is None:
                continue
            numbers = [n for a, b in ranges for n in range(a, b + 1)]
            if len(numbers) == len(recorded):
                unit.publications[topic] = numbers
    return Recording(
        bag.path,
        bag.storage,
        units,
        bag.custom,
        count,
        bag.connections,
        raw_messages,
        digests,
        last * 1e-9 if last >= 0 else None,
        first * 1e-9 if first >= 0 else None,
    )
