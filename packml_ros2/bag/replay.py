"""``packml replay <bag> --check``: feed a recording's inputs to a fresh engine and compare.

Per unit in the bag:

1. the configuration comes from the recorded ``config`` topic (the cell file the unit was started
   with), or from ``--config <cell.yaml>`` (which takes precedence when given);
2. a fresh :class:`~packml_ros2.core.Unit` is built on the bag's own clock: frozen at the time of
   the ``start`` input, with a memory store whose ``load()`` returns the persistence document the
   recorded unit had restored — if the recorded unit had a store (the ``start`` input says so:
   the store's periodic saves are engine deadlines too, and every deadline publishes what
   changed); its start-up outputs are emitted as the node does;
3. every input of ``input_log`` (in index order) is applied by the same
   :class:`~packml_ros2.driver.UnitDriver` the node uses, at its recorded time; before each input
   the engine's deadlines are fired one at a time, each with the clock at its own time (as the
   node's 50 ms timer does; catching up to the input's time at once would skip periodic
   deadlines after long idle gaps); after the last input, deadlines are fired up to the end of
   the recording (its last recorded output or input);
4. the replayed outputs (``status``, ``transitions``, ``alarms``, ``admin``) are compared with the
   recorded ones message by message, on decoded values: serialized bytes with the padding ignored
   (:mod:`.cdr`; CDR padding bytes are unset and differ between writers), and when those differ,
   the decoded messages field by field.

Alignment of recorded outputs (a recorder may join late or stop early):

- The input log must be complete: indices 1..n without gaps, starting with ``start`` (a recorder
  gets it from the unit's start through transient-local history, 5000 deep). Otherwise the bag
  is refused.
- Start of each output topic: with our recorder's notes (``custom_data``) every recorded message
  carries its DDS publication sequence number p, and it is compared with the p-th replayed
  message of that topic (exact, also across messages the recorder missed). Without them (bags of
  other recorders/writers) the first recorded message is located in the replayed stream by value
  (the earliest replayed message equal to it, or the first with the same or a later stamp), and
  from there the streams are compared one to one. Replayed messages before it were published
  before the recorder subscribed (transient-local history delivers only the last status, admin
  data and alarm list and the last 100 transitions) and are not compared.
- End: each recorded message must have been replayed. Replayed messages after a topic's last
  recorded message are differences when stamped before the unit's last recorded output (the
  recorder was listening then); stamped at or after it they were in flight when the recording
  stopped and are not compared.
"""

from __future__ import annotations

import array
import contextlib
import copy
import functools
import gc
import hashlib
import itertools
import json
import math
import shutil
import struct
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rclpy.serialization import deserialize_message, serialize_message

from ..core import CellConfig, Unit, UnitConfig, inputlog, load_cell, parse_cell, state_name
from ..core.config import ConfigError
from ..driver import FrozenClock, UnitDriver
from . import cdr
from .cdr import canonical, same_bytes
from .recording import Input, Recording, RecordingError, UnitRecording, load
from .topics import CUSTOM_KEY, OUTPUT_TOPICS, UNIT_TOPICS, msg_class, typestore

OUTPUT_CLASSES = {t: msg_class(UNIT_TOPICS[t]) for t in OUTPUT_TOPICS}
#: Serializers for the comparison: ours for the messages full of shared alarms (4x faster than
#: rclpy's there), rclpy's for the others.
SERIALIZE = {"admin": cdr.serialize, "alarms": cdr.serialize}
MAX_FIELDS = 12
MAX_INPUTS = 12


class MemoryStore:
    """The persistence store of a replayed unit: ``load()`` returns the recorded document."""

    def __init__(self, document: dict[str, Any] | None) -> None:
        self.document = document
        self.saves = 0

    def load(self) -> dict[str, Any] | None:
        return copy.deepcopy(self.document)

    def save(self, document: dict[str, Any], now: float) -> None:
        self.saves += 1

    def close(self) -> None:
        pass


# -- values ------------------------------------------------------------------------------------------
def stamp_of(msg: Any) -> float:
    s = msg.stamp
    return float(s.sec + s.nanosec * 1e-9)


def raw_stamp(raw: bytes) -> float:
    """The leading ``builtin_interfaces/Time stamp`` of a serialized output message."""
    little = len(raw) > 1 and raw[1] & 1
    sec, nanosec = struct.unpack_from("<iI" if little else ">iI", raw, 4)
    return float(sec + nanosec * 1e-9)


def _is_msg(x: Any) -> bool:
    return hasattr(x, "get_fields_and_field_types")


def _plain(x: Any) -> Any:
    """numpy arrays (fixed-size arrays of rclpy messages) and scalars as Python values."""
    tolist = getattr(x, "tolist", None)
    return tolist() if tolist is not None and not isinstance(x, array.array) else x


def diff(a: Any, b: Any, path: str = "", out: list[tuple[str, Any, Any]] | None = None,
         limit: int = MAX_FIELDS) -> list[tuple[str, Any, Any]]:  # fmt: skip
    """Field-level differences between two decoded values: [(path, a, b)] (NaN equals NaN)."""
    out = [] if out is None else out
    if len(out) >= limit:
        return out
    a, b = _plain(a), _plain(b)
    if _is_msg(a) and _is_msg(b):
        for name in a.get_fields_and_field_types():
            diff(getattr(a, name), getattr(b, name), f"{path}.{name}" if path else name, out, limit)
    elif isinstance(a, (str, bytes)) or isinstance(b, (str, bytes)):
        if a != b:
            out.append((path, a, b))
    elif isinstance(a, (list, tuple, array.array)):
        la, lb = list(a), list(b) if isinstance(b, (list, tuple, array.array)) else [b]
        if len(la) != len(lb):
            out.append((f"{path} (length)", len(la), len(lb)))
        for i, (x, y) in enumerate(zip(la, lb, strict=False)):
            diff(x, y, f"{path}[{i}]", out, limit)
    elif isinstance(a, float) or isinstance(b, float):
        if not (a == b or (math.isnan(a) and math.isnan(b))):
            out.append((path, a, b))
    elif a != b:
        out.append((path, a, b))
    return out


def same(raw: bytes, msg: Any) -> bool:
    """Recorded bytes and a replayed message are equal on decoded values."""
    if same_bytes(raw, serialize_message(msg), type(msg)):
        return True
    return not diff(deserialize_message(raw, type(msg)), msg, limit=1)


# -- results ----------------------------------------------------------------------------------------------
@dataclass
class Difference:
    """The first difference on one output topic of one unit."""

    unit: str
    topic: str
    kind: str  # "differs" | "missing" (recorded, not replayed) | "extra" (replayed, not recorded)
    recorded_index: int  # index among the recorded messages of the topic (-1: none)
    replayed_index: int  # index among the replayed messages (-1: none)
    stamp: float
    recorded: Any = None
    replayed: Any = None
    fields: list[tuple[str, Any, Any]] = field(default_factory=list)
    cause: int = 0  # index of the last input applied before the replayed message

    def headline(self, t0: float) -> str:
        where = f"{self.unit}/{self.topic}"
        at = f"t=+{self.stamp - t0:.3f} s"
        if self.kind == "missing":
            return (
                f"{where}: recorded message #{self.recorded_index} ({at}) was not produced by the "
                f"replay (it produced {self.replayed_index} {self.topic} messages)"
            )
        if self.kind == "extra":
            return (
                f"{where}: the replay produced message #{self.replayed_index} ({at}) that the "
                "recording does not have, although the recorder was listening then"
            )
        return f"{where}: message #{self.recorded_index} ({at}) differs from replayed #{self.replayed_index}"


@dataclass
class UnitResult:
    unit: str
    prefix: str
    start_time: float
    inputs: list[Input]
    produced: dict[str, list[Any]]
    causes: dict[str, list[int]]
    compared: dict[str, int]
    not_recorded: dict[str, int]  # replayed before the recording / after it stopped
    windows: dict[str, tuple[int, int]]  # topic -> (first replayed index, end) matched to the bag
    out_end: float
    differences: list[Difference] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.differences

    def first(self) -> Difference | None:
        if not self.differences:
            return None
        order = {t: i for i, t in enumerate(OUTPUT_TOPICS)}
        return min(self.differences, key=lambda d: (d.stamp, order[d.topic]))


@dataclass
class ReplayResult:
    path: Path
    units: list[UnitResult]
    messages: int  # messages in the bag
    seconds: float  # wall time of read + replay + compare

    @property
    def ok(self) -> bool:
        return all(u.ok for u in self.units)

    @property
    def differences(self) -> list[Difference]:
        return [d for u in self.units for d in u.differences]

    def digest(self) -> str:
        """SHA-256 of every replayed output (serialized with the padding zeroed, per unit and
        topic): equal digests mean identical replays (including every admin time)."""
        h = hashlib.sha256()
        for u in self.units:
            for topic in OUTPUT_TOPICS:
                h.update(f"{u.prefix}/{topic}\0".encode())
                cls = OUTPUT_CLASSES[topic]
                for msg in u.produced[topic]:
                    h.update(canonical(bytes(serialize_message(msg)), cls))
        return h.hexdigest()

    def summary(self) -> str:
        parts = []
        for u in self.units:
            n = sum(u.compared.values())
            parts.append(f"{u.unit}: {len(u.inputs)} inputs, {n} outputs compared")
        verdict = "match" if self.ok else "MISMATCH"
        return f"{self.path}: {verdict} ({'; '.join(parts)}; {self.messages} messages, {self.seconds:.2f} s)"

    def report(self) -> str:
        if self.ok:
            return self.summary()
        lines = [self.summary()]
        for u in self.units:
            if u.ok:
                continue
            lines += explain(u)
        return "\n".join(lines)

    def assert_matches(self) -> ReplayResult:
        """Raise AssertionError with the report unless the replay matches the recording."""
        if not self.ok:
            raise AssertionError(self.report())
        return self


def _transition_text(m: Any, t0: float) -> str:
    if m is None:
        return "none"
    modes = f", mode {m.from_mode} -> {m.to_mode}" if m.from_mode != m.to_mode else ""
    cmd = f" {m.command}" if m.command else ""
    src = f" from {m.source}" if m.source else ""
    detail = f" ({m.detail})" if m.detail else ""
    return (
        f"seq {m.sequence} {m.from_state_name} -> {m.to_state_name}{modes} "
        f"[{m.trigger_name}{cmd}{src}]{detail} at t=+{stamp_of(m) - t0:.3f} s"
    )


def _value(topic: str, path: str, v: Any) -> str:
    text = repr(v)
    if path.endswith(("state_current", "from_state", "to_state", "state_requested")) and isinstance(
        v, int
    ):
        text += f" ({state_name(v)})"
    return text if len(text) < 120 else text[:117] + "..."


def explain(u: UnitResult) -> list[str]:
    """The first difference of a unit: what differs, the transition around it, the inputs."""
    d = u.first()
    assert d is not None
    t0 = u.start_time
    lines = [f"first difference: {d.headline(t0)}"]
    for path, a, b in d.fields:
        lines.append(
            f"    {path}: recorded {_value(d.topic, path, a)}, replayed {_value(d.topic, path, b)}"
        )
    # the diverging transition, or the last common one before the difference
    trans = [x for x in u.differences if x.topic == "transitions"]
    produced_t = u.produced["transitions"]
    if trans:
        x = trans[0]
        lines.append("diverging transition:")
        lines.append(f"    recorded: {_transition_text(x.recorded, t0)}")
        lines.append(f"    replayed: {_transition_text(x.replayed, t0)}")
        common_end = x.replayed_index if x.replayed_index >= 0 else len(produced_t)
    else:
        common_end = sum(1 for m in produced_t if stamp_of(m) <= d.stamp)
        lines.append("transitions agree up to the difference")
    start, _ = u.windows.get("transitions", (0, 0))
    last_common = produced_t[common_end - 1] if 0 < common_end <= len(produced_t) else None
    if last_common is not None and common_end - 1 >= start:
        lines.append(f"last common transition: {_transition_text(last_common, t0)}")
    # the inputs that led to it: since the last common transition, up to the difference
    since = stamp_of(last_common) if last_common is not None else -math.inf
    upto = d.cause if d.cause else max((i.index for i in u.inputs if i.time <= d.stamp), default=0)
    led = [i for i in u.inputs if since <= i.time and i.index <= upto]
    if not led:
        led = [i for i in u.inputs if i.index <= upto][-3:]
    lines.append(f"inputs that led to it ({len(led)}):")
    if len(led) > MAX_INPUTS:
        lines.append(f"    ... {len(led) - MAX_INPUTS} earlier")
        led = led[-MAX_INPUTS:]
    for i in led:
        lines.append(f"    #{i.index} t=+{i.time - t0:.3f} s {i.name} {i.args_json}")
    others = [x for x in u.differences if x is not d]
    for x in others:
        lines.append(f"also: {x.headline(t0)}")
    return lines


# -- replaying one unit ----------------------------------------------------------------------------
@functools.lru_cache(maxsize=32)
def _recorded_cell(text: str, source: str) -> CellConfig:
    from ..core.safe_yaml import parse_document
    from ..core.secrets import redact

    # (a bag recorded before units redacted their configuration may hold a secret: drop it)
    return parse_cell(redact(parse_document(text, source)), source)


def plc_unit(rec: UnitRecording) -> bool:
    """Whether ``rec`` was recorded from a PLC unit's bridge (packml_ros2.plc: its ``config``
    says so)."""
    try:
        return "plc" in json.loads(rec.config_json or "{}")
    except ValueError:
        return False


def unit_config(rec: UnitRecording, config_file: str | Path | None, bag: Path) -> UnitConfig:
    """The unit's configuration: ``config_file`` if given, else the recorded cell file."""
    try:
        if config_file is not None:
            cell = load_cell(config_file)
            source = str(config_file)
        elif rec.config_json:
            source = f"{bag}:{rec.prefix}/config"
            cell = _recorded_cell(json.loads(rec.config_json)["cell_yaml"], source)
        else:
            raise RecordingError(
                f"{bag}: unit {rec.prefix} has no recorded configuration ({rec.prefix}/config: the "
                "unit was not started from a cell file); give it with --config <cell.yaml>"
            )
    except ConfigError as exc:
        raise RecordingError(
            f"{bag}: the configuration of {rec.prefix} is not valid: {exc}"
        ) from None
    name = rec.name
    if name not in cell.units:
        raise RecordingError(f"{source} has no unit {name!r} (units: {', '.join(cell.units)})")
    return cell.units[name]


def checked_inputs(rec: UnitRecording, bag: Path) -> list[Input]:
    """The input log in index order; refused unless complete from the unit's start."""
    if plc_unit(rec):
        raise RecordingError(
            f"{bag}: {rec.prefix} is a PLC unit: its state machine ran in the PLC, the bag holds "
            "its outputs only; there is nothing to replay"
        )
    if not rec.inputs:
        raise RecordingError(
            f"{bag}: no input log for {rec.prefix} ({rec.prefix}/input_log is empty or missing; "
            "was the unit started with record_inputs:=false?)"
        )
    inputs = sorted(rec.inputs, key=lambda i: i.index)
    firsts = [i for i in inputs if i.index == 1]
    if len(firsts) > 1:
        raise RecordingError(
            f"{bag}: {rec.prefix} started {len(firsts)} times during the recording (input #1 "
            "appears more than once); replay covers one run of a unit: record each run apart"
        )
    if inputs[0].index != 1 or inputs[0].name != "start":
        raise RecordingError(
            f"{bag}: the input log of {rec.prefix} begins at input #{inputs[0].index}, not at the "
            "unit's start: the recorder joined more than 5000 inputs after the unit started; "
            "record from an earlier point (restart the unit with the recorder running)"
        )
    for a, b in itertools.pairwise(inputs):
        if b.index != a.index + 1:
            raise RecordingError(
                f"{bag}: the input log of {rec.prefix} has a gap: inputs #{a.index + 1}..#{b.index - 1} "
                "are missing (the recorder lost them); record again"
            )
    return upgraded(inputs, rec, bag)


def upgraded(inputs: list[Input], rec: UnitRecording, bag: Path) -> list[Input]:
    """The inputs in the input log's current schema (core.inputlog): bags recorded with an older
    one replay too."""
    schema = inputlog.schema_of(inputs[0].args)
    if schema == inputlog.SCHEMA:
        return inputs
    out = [inputs[0]]
    for i in inputs[1:]:
        try:
            name, fields = inputlog.upgrade(i.name, i.args, schema)
        except (ValueError, KeyError) as exc:
            raise RecordingError(
                f"{bag}: input #{i.index} of {rec.prefix} ({i.name}) cannot be read: {exc}"
            ) from None
        out.append(Input(i.index, i.time, name, json.dumps(fields, separators=(",", ":"))))
    return out


class UnitReplay:
    """A fresh engine on the recording's clock, driven like the node drives it."""

    def __init__(self, config: UnitConfig, start: Input) -> None:
        args = start.args
        self.start_time = float(args.get("time", start.time))
        self.clock = FrozenClock(lambda: self.start_time)
        self.clock.frozen = self.start_time
        document = args.get("document")
        persistence = args.get("persistence")
        if persistence is None:  # a unit node that did not say: its configuration's default
            persistence = document is not None or bool(config.persistence_path)
        # The store matters beyond the document: its periodic saves are engine deadlines.
        self.store = MemoryStore(document) if persistence else None
        self.unit = Unit(config, clock=self.clock, store=self.store)  # type: ignore[arg-type]
        self.clock.frozen = None
        self.outputs: dict[str, list[Any]] = {t: [] for t in OUTPUT_TOPICS}
        self.causes: dict[str, list[int]] = {t: [] for t in OUTPUT_TOPICS}
        self.current = start.index
        self.driver = UnitDriver(self.unit, self.clock, self._emit)
        # what UnitNode._publish_start publishes: the start-up outputs, then the admin data
        self.driver.flush()
        self._emit("admin", self.driver.admin_message())

    def _emit(self, topic: str, msg: Any) -> None:
        out = self.outputs.get(topic)
        if out is not None:  # "log" lines are not outputs
            out.append(msg)
            self.causes[topic].append(self.current)

    def tick(self, until: float) -> None:
        """Fire the deadlines due by ``until`` one at a time, each at its own time."""
        unit, catch_up = self.unit, self.driver.catch_up
        nxt = unit.next_deadline()
        while nxt is not None and nxt <= until:
            catch_up(nxt)
            nxt = unit.next_deadline()

    def run(self, inputs: Iterable[Input], until: float) -> None:
        replay = self.driver.replay
        for i in inputs:
            self.tick(i.time)
            self.current = i.index
            replay(i.time, i.name, json.loads(i.args_json))
        self.tick(until)


def _locate(raw: bytes, produced: Sequence[Any]) -> int:
    """Where the first recorded message is in the replayed stream (see the module docstring)."""
    s = raw_stamp(raw)
    for j, m in enumerate(produced):
        if stamp_of(m) == s and same(raw, m):
            return j
    for j, m in enumerate(produced):
        if stamp_of(m) >= s:
            return j
    return len(produced)


def compare_topic(
    unit: str, topic: str, recorded: list[bytes], pubs: list[int] | None, produced: list[Any],
    causes: list[int], out_end: float,
) -> tuple[Difference | None, int, tuple[int, int]]:  # fmt: skip
    """Compare one topic: (first difference or None, messages compared, replayed window)."""
    cls = OUTPUT_CLASSES[topic]
    ser = SERIALIZE.get(topic, serialize_message)
    n = len(recorded)
    if pubs is not None:
        js: Sequence[int] = [p - 1 for p in pubs]
    else:
        j0 = _locate(recorded[0], produced) if n else len(produced)
        js = range(j0, j0 + n)
    first = js[0] if n else len(produced)
    for k, (raw, j) in enumerate(zip(recorded, js, strict=True)):
        if j >= len(produced):
            rec = deserialize_message(raw, cls)
            return (
                Difference(unit, topic, "missing", k, len(produced), stamp_of(rec), rec),
                k,
                (first, j),
            )
        m = produced[j]
        if same_bytes(raw, ser(m), cls):
            continue
        rec = deserialize_message(raw, cls)
        if rec == m:
            continue
        fields = diff(rec, m)
        if fields:
            d = Difference(unit, topic, "differs", k, j, min(stamp_of(rec), stamp_of(m)), rec, m,
                           fields, causes[j])  # fmt: skip
            return d, k, (first, j)
    end = (js[-1] + 1) if n else first
    if n == 0:
        end = 0
    for j in range(end, len(produced)):
        m = produced[j]
        if stamp_of(m) < out_end:
            d = Difference(unit, topic, "extra", -1, j, stamp_of(m), None, m, [], causes[j])
            return d, n, (first, end)
        break
    return None, n, (first, end)


def replay_unit(rec: UnitRecording, bag: Path, config_file: str | Path | None = None,
                until: float | None = None) -> UnitResult:  # fmt: skip
    config = unit_config(rec, config_file, bag)
    inputs = checked_inputs(rec, bag)
    stamps = [raw_stamp(raw) for msgs in rec.outputs.values() for raw in msgs]
    out_end = max(stamps, default=-math.inf)
    end = max(out_end, inputs[-1].time) if until is None else until
    r = UnitReplay(config, inputs[0])
    r.run(inputs[1:], end)
    name = config.name
    result = UnitResult(
        name, rec.prefix, r.start_time, inputs, r.outputs, r.causes, {}, {}, {}, out_end
    )
    for topic in OUTPUT_TOPICS:
        if topic not in rec.outputs:
            continue  # not recorded (e.g. a bag of another recorder without it): not compared
        d, n, window = compare_topic(name, topic, rec.outputs[topic], rec.publications.get(topic),
                                     r.outputs[topic], r.causes[topic], out_end)  # fmt: skip
        result.compared[topic] = n
        result.windows[topic] = window
        result.not_recorded[topic] = len(r.outputs[topic]) - n
        if d is not None:
            result.differences.append(d)
    return result


def replay(path: str | Path, config: str | Path | None = None, units: Sequence[str] = (),
           recording: Recording | None = None) -> ReplayResult:  # fmt: skip
    """Replay-check the bag at ``path`` offline (every unit in it, or ``units``)."""
    with gc_paused():
        return _replay(path, config, units, recording)


@contextlib.contextmanager
def gc_paused() -> Iterator[None]:
    """The cyclic garbage collector off for the duration: an offline check allocates hundreds of
    thousands of objects it keeps (recorded bytes, replayed messages), and the collections that
    triggers rescan all of them over and over (15-20 % of the check's time). Reference counting
    still frees everything; what forms cycles is collected when the collector is back on."""
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()


def _replay(path: str | Path, config: str | Path | None, units: Sequence[str],
            recording: Recording | None) -> ReplayResult:  # fmt: skip
    t = time.perf_counter()
    rec = recording if recording is not None else load(path, em_reports=False)
    if units:
        chosen = [rec.unit(u) for u in units]
    else:  # units whose topics hold nothing were not running while recording (a cell's); a PLC
        # unit's state machine ran in its PLC: the bag has its outputs, nothing to replay
        chosen = [
            u for u in rec.units.values()
            if (u.inputs or u.config_json or any(u.outputs.values())) and not plc_unit(u)
        ]  # fmt: skip
    if not chosen:
        raise RecordingError(
            f"{path}: no PackML unit topics in the bag (/<cell>/<unit>/input_log ...)"
        )
    until = rec.custom.get("replay_until", {})
    results = [replay_unit(u, rec.path, config, until.get(u.prefix)) for u in chosen]
    return ReplayResult(Path(path), results, rec.message_count, time.perf_counter() - t)


# -- --update ------------------------------------------------------------------------------------------
def update(path: str | Path, out: str | Path | None = None, config: str | Path | None = None,
           storage: str | None = None) -> tuple[ReplayResult, Path]:  # fmt: skip
    """Rewrite the recorded outputs with the replayed ones (into ``out``, or in place for a bag
    directory). Inputs, configuration and other topics are copied unchanged."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    src = Path(path)
    rec = load(src, keep_raw=True)
    result = replay(src, config, recording=rec)
    in_place = out is None
    if in_place and not (src.is_dir() and (src / "metadata.yaml").exists()):
        raise RecordingError(f"{src} is not a bag directory: give the output with -o")
    # in place: written under a temporary directory with the bag's own name, so the storage file
    # inside is named after the bag, as a recorder names it
    staging = src.with_name(src.name + ".update-tmp")
    dst = staging / src.name if in_place else Path(out)  # type: ignore[arg-type]
    if dst.exists() or (in_place and staging.exists()):
        raise RecordingError(f"{staging if in_place else dst} exists already")
    kind = storage or rec.storage
    plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
    if in_place:
        staging.mkdir()
    writer = Writer(dst, version=9, storage_plugin=plugin)
    writer.open()
    try:
        _write_update(writer, rec, result)
    except BaseException:
        writer.abort()
        shutil.rmtree(staging if in_place else dst, ignore_errors=True)
        raise
    if in_place:
        old = src.with_name(src.name + ".update-old")
        src.rename(old)
        dst.rename(src)
        shutil.rmtree(old)
        staging.rmdir()
        dst = src
    return result, dst


def _write_update(writer: Any, rec: Recording, result: ReplayResult) -> None:
    store = typestore()
    conns: dict[str, Any] = {}
    for c in rec.connections:
        if c.topic in conns:
            continue
        qos = list(getattr(c.ext, "offered_qos_profiles", []) or [])
        try:
            conns[c.topic] = writer.add_connection(
                c.topic, c.msgtype, typestore=store, offered_qos_profiles=qos
            )
        except Exception:  # a type we do not know: its stored definition
            digest = c.digest or rec.digests.get(c.msgtype, "")
            if not (c.msgdef.data and digest):
                raise RecordingError(
                    f"{c.topic}: type {c.msgtype} is neither installed nor defined in the bag"
                ) from None
            conns[c.topic] = writer.add_connection(
                c.topic, c.msgtype, msgdef=c.msgdef.data, rihs01=digest, offered_qos_profiles=qos
            )
    replaced = {f"{u.prefix}/{t}" for u in result.units for t in u.windows}
    items: list[tuple[int, int, str, bytes]] = []
    order = 0
    for conn, ts, raw in rec.raw_messages:
        if conn.topic not in replaced:
            items.append((ts, order, conn.topic, raw))
            order += 1
    publications: dict[str, list[list[int]]] = {}
    for u in result.units:
        for topic, (first, _) in u.windows.items():
            msgs = [m for m in u.produced[topic][first:] if stamp_of(m) <= u.out_end]
            last = 0
            for m in msgs:
                ts = max(round(stamp_of(m) * 1e9), last + 1)
                last = ts
                items.append((ts, order, f"{u.prefix}/{topic}", bytes(serialize_message(m))))
                order += 1
            if msgs:
                publications[f"{u.prefix}/{topic}"] = [[first + 1, first + len(msgs)]]
    items.sort()
    for ts, _, topic, raw in items:
        writer.write(conns[topic], ts, raw)
    notes = dict(rec.custom)
    notes.update(
        {"version": 1, "publications": publications, "updated_by": "packml replay --update"}
    )
    writer.set_custom_data(CUSTOM_KEY, json.dumps(notes, separators=(",", ":")))
    writer.close()
