"""``packml replay <bag> --check``: feed a recording's inputs to an engine and compare.

Per unit in the bag:

1. the configuration comes from the recorded ``config`` topic (the cell file the unit was started
   with), or from ``--config <cell.yaml>`` (which takes precedence when given);
2. the origin: where the replay starts (:func:`starting_point`). The unit's start when the bag
   holds the input log from its ``start`` input on: a fresh :class:`~packml_ros2.core.Unit` on
   the bag's own clock, frozen at the time of the ``start`` input, with a memory store whose
   ``load()`` returns the persistence document the recorded unit had restored — if the recorded
   unit had a store (the ``start`` input says so: the store's periodic saves are engine
   deadlines too, and every deadline publishes what changed); its start-up outputs are emitted
   as the node does. Otherwise (the recorder joined a unit that had run more inputs than the
   input log's history keeps) the earliest snapshot of the unit's engine state
   (``<unit>/snapshot``, :mod:`packml_ros2.core.snapshot`; the unit publishes one whenever a
   recorder joins) after which every input is in the bag: the engine is restored from it;
3. every input after the origin (in index order) is applied by the same
   :class:`~packml_ros2.driver.UnitDriver` the node uses, at its recorded time; before each input
   the engine's deadlines are fired one at a time, each with the clock at its own time (as the
   node's 50 ms timer does; catching up to the input's time at once would skip periodic
   deadlines after long idle gaps); after the last input, deadlines are fired up to the
   recorder's stop;
4. the replayed outputs (``status``, ``transitions``, ``alarms``, ``admin``) are compared with the
   recorded ones message by message, on decoded values: serialized bytes with the padding ignored
   (:mod:`.cdr`; CDR padding bytes are unset and differ between writers), and when those differ,
   the decoded messages field by field.

Alignment of recorded outputs (a recorder joins late and stops):

- Inputs: from the origin on, indices without gaps. Otherwise the bag is refused.
- Start of each output topic: with our recorder's notes (``custom_data``) every recorded message
  carries its DDS publication sequence number p, and it is compared with the replayed message
  p - n (n: what the unit had published on the topic before the origin, 0 at its start; the
  snapshot says) — exact, also across messages the recorder missed; recorded messages published
  before the origin (the latched history a late recorder gets) are not compared. Without notes
  (bags of other recorders/writers) the first recorded message published after the origin is
  located in the replayed stream by value (the earliest replayed message equal to it, or the
  first with the same or a later stamp), and from there the streams are compared one to one.
  Replayed messages before it were published before the recorder subscribed (transient-local
  history delivers only the last status, admin data and alarm list and the last 100 transitions)
  and are not compared.
- End: each recorded message must have been replayed, and every replayed message stamped before
  the recorder's stop (its notes) must have been recorded: a deleted last transition and an
  added final status are both differences. Our recorder writes exactly the outputs stamped
  before its stop. A bag without the stop time is compared up to
  :data:`~.recording.FOREIGN_MARGIN` before its last message, and at least up to the unit's
  last input in it.
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
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rclpy.serialization import deserialize_message, serialize_message

from ..core import (
    CellConfig,
    Unit,
    UnitConfig,
    inputlog,
    load_cell,
    parse_cell,
    snapshot,
    state_name,
)
from ..core.config import ConfigError
from ..core.unit import Trigger
from ..driver import SNAPSHOT_SCHEMA, FrozenClock, UnitDriver
from . import cdr
from .cdr import canonical, raw_stamp, same_bytes
from .recording import (
    FOREIGN_MARGIN,
    Input,
    Recording,
    RecordingError,
    Snapshot,
    UnitRecording,
    load,
)
from .topics import (
    CUSTOM_KEY,
    OUTPUT_TOPICS,
    UNIT_TOPICS,
    close_writer,
    msg_class,
    open_writer,
    typestore,
)

OUTPUT_CLASSES = {t: msg_class(UNIT_TOPICS[t]) for t in OUTPUT_TOPICS}
#: Serializers for the comparison: ours (:func:`.cdr.serialize`, generated from the message
#: definitions) for every output, faster than rclpy's (4x on the messages full of shared alarms,
#: 1.3-1.5x on statuses and transitions).
SERIALIZE = dict.fromkeys(OUTPUT_TOPICS, cdr.serialize)
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


# -- values ----------------------------------------------------------------------------------------
def stamp_of(msg: Any) -> float:
    s = msg.stamp
    return float(s.sec + s.nanosec * 1e-9)


def _is_msg(x: Any) -> bool:
    return hasattr(x, "get_fields_and_field_types")


def _plain(x: Any) -> Any:
    """numpy arrays (fixed-size arrays of rclpy messages) and scalars as Python values."""
    tolist = getattr(x, "tolist", None)
    return tolist() if tolist is not None and not isinstance(x, array.array) else x


def diff(
    a: Any,
    b: Any,
    path: str = "",
    out: list[tuple[str, Any, Any]] | None = None,
    limit: int = MAX_FIELDS,
) -> list[tuple[str, Any, Any]]:
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


# -- results ---------------------------------------------------------------------------------------
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
    stop: float  # outputs published up to here are compared (the recorder's stop)
    origin: Origin
    differences: list[Difference] = field(default_factory=list)
    #: recorded messages published before the origin (a snapshot): not compared
    before_origin: dict[str, int] = field(default_factory=dict)

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
            since = (
                f" from a snapshot after input #{u.origin.index}" if u.origin.start is None else ""
            )
            parts.append(f"{u.unit}: {len(u.inputs)} inputs{since}, {n} outputs compared")
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


def _named(number: int, name: str, namer: Callable[[int], str]) -> str:
    """A state (mode, trigger) by its number, as the field diff shows it; the message's own name
    field too when it says something else (a hand-edited bag)."""
    text = namer(number)
    return text if name in ("", text) else f"{text} (named {name!r} in the message)"


def _trigger_name(number: int) -> str:
    try:
        return Trigger(number).name
    except ValueError:
        return f"TRIGGER_{number}"


def _transition_text(m: Any, t0: float) -> str:
    if m is None:
        return "none"
    modes = f", mode {m.from_mode} -> {m.to_mode}" if m.from_mode != m.to_mode else ""
    cmd = f" {m.command}" if m.command else ""
    src = f" from {m.source}" if m.source else ""
    detail = f" ({m.detail})" if m.detail else ""
    frm = _named(m.from_state, m.from_state_name, state_name)
    to = _named(m.to_state, m.to_state_name, state_name)
    trigger = _named(m.trigger, m.trigger_name, _trigger_name)
    return (
        f"seq {m.sequence} {frm} -> {to}{modes} [{trigger}{cmd}{src}]{detail} "
        f"at t=+{stamp_of(m) - t0:.3f} s"
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


@dataclass
class Origin:
    """Where a replay starts: the unit's start (its ``start`` input, index 0) or a snapshot of
    its engine state taken after input ``index``."""

    index: int
    time: float
    start: Input | None = None
    #: the snapshot's JSON object (``engine``, ``persistence``, ``input_schema``, ``published``)
    state: dict[str, Any] | None = None
    #: per output topic, how many messages the unit had published before the origin
    published: dict[str, int] = field(default_factory=dict)


def _refuse_plc(rec: UnitRecording, bag: Path) -> None:
    if plc_unit(rec):
        raise RecordingError(
            f"{bag}: {rec.prefix} is a PLC unit: its state machine ran in the PLC, the bag holds "
            "its outputs only; there is nothing to replay"
        )


def check_log(entries: Sequence[tuple[int, float, str]], where: str) -> list[int]:
    """The order of a recorded input log's entries ``(index, time, name)`` (in bag order) by
    index, after the checks every log must pass; :class:`RecordingError` with the reason:
    ``restarted`` (a ``start`` record #1 after other inputs: the log begins again),
    ``duplicate_input`` (an index twice), ``stamps_out_of_order`` (a later index stamped
    earlier, unless it records a step of the wall clock)."""
    for k, (index, _, name) in enumerate(entries):
        if index == 1 and name == inputlog.START and k > 0:
            raise RecordingError(
                f"{where} started more than once during the recording (its input log begins "
                "again at #1); replay covers one run: record each run apart",
                "restarted",
            )
    order = sorted(range(len(entries)), key=lambda k: entries[k][0])
    for a, b in itertools.pairwise(order):
        (ia, ta, _), (ib, tb, nb) = entries[a], entries[b]
        if ia == ib:
            raise RecordingError(
                f"{where}: input #{ib} is in the recording twice (messages {a + 1} and {b + 1} "
                "of its input log): the bag was written by something else than a recorder, or "
                "edited",
                "duplicate_input",
            )
        if tb < ta and nb != inputlog.CLOCK_STEP.name:  # (a step back is stamped back)
            raise RecordingError(
                f"{where}: input #{ib} is stamped {ta - tb:.6f} s before input #{ia}: the stamps "
                "of an input log never go back (the bag was edited, or its writer is broken)",
                "stamps_out_of_order",
            )
    return order


def _sorted_inputs(rec: UnitRecording, bag: Path) -> list[Input]:
    order = check_log([(i.index, i.time, i.name) for i in rec.inputs], f"{bag}: {rec.prefix}")
    return [rec.inputs[k] for k in order]


def checked_inputs(rec: UnitRecording, bag: Path) -> list[Input]:
    """The input log in index order, complete from the unit's start (``--live`` replays that
    only: it drives a freshly started unit)."""
    _refuse_plc(rec, bag)
    origin, inputs = starting_point(rec, bag)
    if origin.start is None:
        raise RecordingError(
            f"{bag}: the recording of {rec.prefix} starts from a snapshot of its state after input "
            f"#{origin.index}, not at the unit's start: --live drives a freshly started unit; "
            "check this bag offline (packml replay --check)"
        )
    return inputs


def starting_point(rec: UnitRecording, bag: Path) -> tuple[Origin, list[Input]]:
    """Where the replay of ``rec`` starts and the inputs after it (current schema). The earliest
    origin from which every later input is in the bag: the unit's start, else the earliest
    snapshot. Refused (:class:`RecordingError`) when there is none."""
    _refuse_plc(rec, bag)
    inputs = _sorted_inputs(rec, bag)
    if not inputs and not rec.snapshots:
        raise RecordingError(
            f"{bag}: no input log for {rec.prefix} ({rec.prefix}/input_log is empty or missing; "
            "was the unit started with record_inputs:=false?)"
        )
    present = [i.index for i in inputs]
    last = present[-1] if present else 0
    # the lowest index from which every input up to the last one is in the bag
    tail = last + 1
    for k in range(len(present) - 1, -1, -1):
        if present[k] != tail - 1:
            break
        tail = present[k]
    if inputs and inputs[0].index == 1 and inputs[0].name == inputlog.START and tail == 1:
        start = inputs[0]
        origin = Origin(0, float(start.args.get("time", start.time)), start=start)
        return origin, upgraded(inputs, inputlog.schema_of(start.args), rec, bag)
    usable = [snap for snap in rec.snapshots if snap.index + 1 >= tail]
    if usable:
        snap = min(usable, key=lambda x: (x.index, x.time))
        origin = _snapshot_origin(snap, rec, bag)
        after = [i for i in inputs if i.index > snap.index]
        schema = int(origin.state.get("input_schema", inputlog.SCHEMA)) if origin.state else 0
        return origin, upgraded(after, schema, rec, bag, first=False)
    if tail > present[0]:  # inputs before the tail: a gap ends where the tail begins
        before = max(i for i in present if i < tail)
        raise RecordingError(
            f"{bag}: the input log of {rec.prefix} has a gap: inputs #{before + 1}..#{tail - 1} "
            "are missing (the recorder lost them) and no snapshot of the unit's state follows "
            "it; record again",
            "missing_input",
        )
    raise RecordingError(
        f"{bag}: the input log of {rec.prefix} begins at input #{present[0]}, not at the unit's "
        f"start, and the bag holds no snapshot of its state ({rec.prefix}/snapshot) to start "
        "from: the unit runs a version that does not publish one, or the recorder did not "
        "subscribe to it; record it again with packml record",
        "missing_input",
    )


def _snapshot_origin(snap: Snapshot, rec: UnitRecording, bag: Path) -> Origin:
    where = f"{bag}: the snapshot of {rec.prefix} (after input #{snap.index})"
    try:
        state = json.loads(snap.state_json)
    except ValueError as exc:
        raise RecordingError(f"{where} is not JSON: {exc}") from None
    if not isinstance(state, dict) or not isinstance(state.get("engine"), dict):
        raise RecordingError(f"{where} holds no engine state")
    schema = state.get("schema")
    if schema != SNAPSHOT_SCHEMA:
        raise RecordingError(
            f"{where} has schema {schema!r}; this version reads {SNAPSHOT_SCHEMA}: replay "
            "it with the version that recorded it"
        )
    published = state.get("published")
    if not isinstance(published, dict) or not all(
        isinstance(published.get(t), int) and published[t] >= 0 for t in OUTPUT_TOPICS
    ):
        raise RecordingError(f"{where} does not say how many messages the unit had published")
    return Origin(
        snap.index, snap.time, state=state, published={t: published[t] for t in OUTPUT_TOPICS}
    )


def upgraded(
    inputs: list[Input], schema: int, rec: UnitRecording, bag: Path, first: bool = True
) -> list[Input]:
    """The inputs (of input log ``schema``) in the current schema (core.inputlog): bags recorded
    with an older one replay too. ``first``: the first input is the ``start`` record."""
    if schema == inputlog.SCHEMA or not inputs:
        return inputs
    out = inputs[:1] if first else []
    for i in inputs[1:] if first else inputs:
        try:
            name, fields = inputlog.upgrade(i.name, i.args, schema)
        except (ValueError, KeyError) as exc:
            raise RecordingError(
                f"{bag}: input #{i.index} of {rec.prefix} ({i.name}) cannot be read: {exc}"
            ) from None
        out.append(Input(i.index, i.time, name, json.dumps(fields, separators=(",", ":"))))
    return out


def _before_holders(schema: Any) -> bool:
    """Whether a unit of input log ``schema`` named its interlock transitions' source
    ``interlock`` (core/inputlog.py): the replayed engine does the same."""
    return not isinstance(schema, int) or schema < inputlog.INTERLOCK_HOLDER_SCHEMA


class UnitReplay:
    """An engine on the recording's clock, driven like the node drives it: a fresh one at the
    unit's start, or the one a snapshot describes."""

    def __init__(self, config: UnitConfig, origin: Origin) -> None:
        self.start_time = origin.time
        self.clock = FrozenClock(lambda: self.start_time)
        self.clock.frozen = self.start_time
        self.outputs: dict[str, list[Any]] = {t: [] for t in OUTPUT_TOPICS}
        self.causes: dict[str, list[int]] = {t: [] for t in OUTPUT_TOPICS}
        self.current = origin.index
        if origin.start is None:
            assert origin.state is not None
            # The store matters beyond its document: its periodic saves are engine deadlines.
            self.store = MemoryStore(None) if origin.state.get("persistence") else None
            try:
                self.unit = snapshot.restore(config, self.clock, origin.state["engine"], self.store)
            except snapshot.SnapshotError as exc:
                raise RecordingError(
                    f"the snapshot of {config.name} after input #{origin.index}: {exc}"
                ) from None
            schema = origin.state.get("input_schema", inputlog.SCHEMA)
            self.unit.legacy_interlock_source = _before_holders(schema)
            self.clock.frozen = None
            self.driver = UnitDriver(self.unit, self.clock, self._emit)
            return
        args = origin.start.args
        document = args.get("document")
        persistence = args.get("persistence")
        if persistence is None:  # a unit node that did not say: its configuration's default
            persistence = document is not None or bool(config.persistence_path)
        self.store = MemoryStore(document) if persistence else None
        self.unit = Unit(config, clock=self.clock, store=self.store)  # type: ignore[arg-type]
        self.unit.legacy_interlock_source = _before_holders(inputlog.schema_of(args))
        self.clock.frozen = None
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
        step = inputlog.CLOCK_STEP.name
        for i in inputs:
            args = json.loads(i.args_json)
            # (a step of the wall clock: what was due by its instant on the old timeline first)
            self.tick(i.time - float(args["offset"]) if i.name == step else i.time)
            self.current = i.index
            replay(i.time, i.name, args)
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
    unit: str,
    topic: str,
    recorded: list[bytes],
    pubs: list[int] | None,
    produced: list[Any],
    causes: list[int],
    stop: float,
    origin: Origin,
) -> tuple[Difference | None, int, tuple[int, int], int]:
    """Compare one topic: (first difference or None, messages compared, replayed window,
    recorded messages published before the origin: not compared)."""
    cls = OUTPUT_CLASSES[topic]
    ser = SERIALIZE.get(topic, serialize_message)
    offset = origin.published.get(topic, 0)
    if pubs is not None:  # the publication numbers of our recorder: exact
        pairs = [(k, p - 1 - offset) for k, p in enumerate(pubs) if p > offset]
    else:  # by content, from the first recorded message published after the origin
        k0 = 0
        if origin.start is None:
            while k0 < len(recorded) and raw_stamp(recorded[k0]) <= origin.time:
                k0 += 1
        j0 = _locate(recorded[k0], produced) if k0 < len(recorded) else len(produced)
        pairs = [(k, j0 + k - k0) for k in range(k0, len(recorded))]
    before = len(recorded) - len(pairs)
    first = pairs[0][1] if pairs else len(produced)
    for n, (k, j) in enumerate(pairs):
        raw = recorded[k]
        if j >= len(produced):
            rec = deserialize_message(raw, cls)
            d = Difference(unit, topic, "missing", k, len(produced), stamp_of(rec), rec)
            return d, n, (first, j), before
        m = produced[j]
        if same_bytes(raw, ser(m), cls):
            continue
        rec = deserialize_message(raw, cls)
        if rec == m:
            continue
        fields = diff(rec, m)
        if fields:
            d = Difference(
                unit,
                topic,
                "differs",
                k,
                j,
                min(stamp_of(rec), stamp_of(m)),
                rec,
                m,
                fields,
                causes[j],
            )
            return d, n, (first, j), before
    # Everything the unit published after the last recorded message, up to the recorder's stop,
    # must have been recorded (a recorder that joined late got the latest as history).
    end = pairs[-1][1] + 1 if pairs else 0
    for j in range(end, len(produced)):
        m = produced[j]
        if stamp_of(m) < stop:
            d = Difference(unit, topic, "extra", -1, j, stamp_of(m), None, m, [], causes[j])
            return d, len(pairs), (first, end), before
        break
    return None, len(pairs), (first, end), before


def replay_unit(
    rec: UnitRecording,
    bag: Path,
    config_file: str | Path | None = None,
    stop: float | None = None,
    end: float | None = None,
) -> UnitResult:
    """Replay one unit from its origin and compare what it published up to ``stop`` (the
    recorder's stop time); without one, up to :data:`~.recording.FOREIGN_MARGIN` before the
    bag's ``end`` (its last message), and at least up to the unit's last input."""
    config = unit_config(rec, config_file, bag)
    origin, inputs = starting_point(rec, bag)
    if stop is None:
        last_input = inputs[-1].time if inputs else origin.time
        stop = max(
            -math.inf if end is None else end - FOREIGN_MARGIN,
            math.nextafter(last_input, math.inf),
        )
    r = UnitReplay(config, origin)
    # (up to the last recorded output too: every recorded message must be produced)
    last = max((raw_stamp(msgs[-1]) for msgs in rec.outputs.values() if msgs), default=-math.inf)
    r.run(inputs if origin.start is None else inputs[1:], max(stop, origin.time, last))
    name = config.name
    result = UnitResult(
        name, rec.prefix, r.start_time, inputs, r.outputs, r.causes, {}, {}, {}, stop, origin
    )
    for topic in OUTPUT_TOPICS:
        if topic not in rec.outputs:
            continue  # not recorded (e.g. a bag of another recorder without it): not compared
        produced = r.outputs[topic]
        upgrade = rec.upgrades.get(topic)
        if upgrade is not None:  # an older definition: only the fields it had are compared
            produced = [upgrade.mask(m) for m in produced]
        d, n, window, before = compare_topic(
            name,
            topic,
            rec.outputs[topic],
            rec.publications.get(topic),
            produced,
            r.causes[topic],
            stop,
            origin,
        )
        result.compared[topic] = n
        result.windows[topic] = window
        result.not_recorded[topic] = len(r.outputs[topic]) - n
        result.before_origin[topic] = before
        if d is not None:
            result.differences.append(d)
    return result


def replay(
    path: str | Path,
    config: str | Path | None = None,
    units: Sequence[str] = (),
    recording: Recording | None = None,
) -> ReplayResult:
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


def _replay(
    path: str | Path, config: str | Path | None, units: Sequence[str], recording: Recording | None
) -> ReplayResult:
    t = time.perf_counter()
    rec = recording if recording is not None else load(path, em_reports=False)
    if units:
        chosen = [rec.unit(u) for u in units]
    else:  # units whose topics hold nothing were not running while recording (a cell's); a PLC
        # unit's state machine ran in its PLC: the bag has its outputs, nothing to replay
        chosen = [
            u
            for u in rec.units.values()
            if (u.inputs or u.config_json or any(u.outputs.values())) and not plc_unit(u)
        ]
    if not chosen:
        raise RecordingError(
            f"{path}: no PackML unit topics in the bag (/<cell>/<unit>/input_log ...)"
        )
    results = [replay_unit(u, rec.path, config, rec.stop, rec.end) for u in chosen]
    return ReplayResult(Path(path), results, rec.message_count, time.perf_counter() - t)


# -- --update --------------------------------------------------------------------------------------
def update(
    path: str | Path,
    out: str | Path | None = None,
    config: str | Path | None = None,
    storage: str | None = None,
) -> tuple[ReplayResult, Path]:
    """Rewrite the recorded outputs with the replayed ones (into ``out``, or in place for a bag
    directory). Inputs, configuration and other topics are copied unchanged."""
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
    if in_place:
        staging.mkdir()
    writer = open_writer(dst, kind)
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
            msgs = [m for m in u.produced[topic][first:] if stamp_of(m) < u.stop]
            last = 0
            for m in msgs:
                ts = max(round(stamp_of(m) * 1e9), last + 1)
                last = ts
                items.append((ts, order, f"{u.prefix}/{topic}", bytes(serialize_message(m))))
                order += 1
            if msgs:
                offset = u.origin.published.get(topic, 0)
                publications[f"{u.prefix}/{topic}"] = [
                    [offset + first + 1, offset + first + len(msgs)]
                ]
    items.sort()
    for ts, _, topic, raw in items:
        writer.write(conns[topic], ts, raw)
    notes = dict(rec.custom)
    notes.update(
        {"version": 1, "publications": publications, "updated_by": "packml replay --update"}
    )
    stops = [u.stop for u in result.units]
    if stops and "stopped_at_ns" not in notes:  # (another recorder's bag: where it was compared)
        notes["stopped_at_ns"] = round(min(stops) * 1e9)
    writer.set_custom_data(CUSTOM_KEY, json.dumps(notes, separators=(",", ":")))
    close_writer(writer)
