"""Record and replay a line's performance: the coordinator's ``line/input_log`` (its inputs),
``line/snapshot`` (its state when the recorder joined) and its outputs ``line/episodes`` and
``line/losses``.

``packml record <cell>`` records these topics beside the units' (:func:`topics`). ``packml
replay`` then also replays the line (:func:`check`), as it replays a unit:

- the origin: the coordinator's ``start`` input when the input log reaches back to it (a fresh
  :class:`~packml_ros2.core.line.performance.Performance` with the open state and running windows
  the coordinator had restored), else the earliest snapshot of the line's state
  (:mod:`packml_ros2.core.line.snapshot`; the coordinator publishes one when a recorder joins)
  after which every input is in the bag — a line that has run for days replays from it;
- every input after the origin is applied again on its recorded time through the same
  :func:`~packml_ros2.core.line.inputs.apply`, and every episode change and publication of losses
  is made again as the coordinator makes them (:mod:`packml_ros2.line_msgs`);
- the streams are compared on decoded values, to the end: with our recorder's notes each
  recorded message carries its publication number p and is compared with the replayed message
  p - n (n: what the coordinator had published before the origin, the snapshot says); recorded
  messages published before the origin (the latched history) are not compared. Without notes the
  first recorded message after the origin is looked for in the replayed stream. Every replayed
  message stamped before the recorder's stop must be in the bag (without a stop: before the
  bag's last message less :data:`~.recording.FOREIGN_MARGIN`, and at least up to the last input).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rclpy.serialization import deserialize_message

from .. import line_msgs
from ..core import ConfigError, load_cell, parse_cell
from ..core.config import CellConfig
from ..core.line import inputs
from ..core.line import snapshot as line_snapshot
from ..core.line.ledger import Ledger
from ..core.line.line import episode_view, published_windows
from ..core.line.performance import Performance
from ..core.snapshot import SnapshotError
from .recording import FOREIGN_MARGIN, RecordingError
from .topics import msg_class

#: topic (relative to ``/<cell>/coordinator``) -> (kind in topics.PUBLISHER_QOS, ROS type)
LINE_TOPICS: dict[str, tuple[str, str]] = {
    "line/input_log": ("line_input_log", "packml_interfaces/msg/UnitInput"),
    "line/episodes": ("line_episodes", "packml_interfaces/msg/LineEpisode"),
    "line/losses": ("line_losses", "packml_interfaces/msg/LineLosses"),
    "line/snapshot": ("snapshot", "packml_interfaces/msg/UnitSnapshot"),
}
#: The line's outputs, compared to the end of the recording.
LINE_OUTPUTS = ("line/episodes", "line/losses")
#: Schema of the JSON object a line's ``UnitSnapshot`` carries (core.line.Line.snapshot).
SNAPSHOT_SCHEMA = 1
MAX_SHOWN = 8


def topics(cell: str) -> list[tuple[str, str, str]]:
    """(topic, kind, type) of what a recorder of ``cell`` records of its line."""
    base = f"/{cell.strip('/')}/coordinator"
    return [(f"{base}/{name}", kind, type_name) for name, (kind, type_name) in LINE_TOPICS.items()]


def line_of(topic: str) -> tuple[str, str] | None:
    """``/<cell>/coordinator/line/<name>`` -> (cell, ``line/<name>``), else None."""
    for name in LINE_TOPICS:
        suffix = f"/coordinator/{name}"
        if topic.endswith(suffix) and topic.count("/") == 4:
            return topic[1 : -len(suffix)], name
    return None


def stamp_reader(name: str) -> Callable[[bytes], float]:
    """The ``stamp`` (seconds) of a serialized message of line output ``name`` (the recorder
    keeps what was stamped before its stop, as it does for the units' outputs)."""
    cls = msg_class(LINE_TOPICS[name][1])

    def read(raw: bytes) -> float:
        try:
            return line_msgs.ns_of(deserialize_message(raw, cls).stamp) * 1e-9
        except Exception:  # (a damaged message: kept, the replay reports it)
            return -math.inf

    return read


@dataclass
class LineRecording:
    cell: str
    inputs: list[Any] = field(default_factory=list)  # UnitInput messages, in bag order
    episodes: list[Any] = field(default_factory=list)
    losses: list[Any] = field(default_factory=list)
    snapshots: list[Any] = field(default_factory=list)  # UnitSnapshot messages
    config_yaml: str | None = None
    #: output ("episodes", "losses") -> publication number of each recorded message (our recorder)
    publications: dict[str, list[int]] = field(default_factory=dict)
    stop: float | None = None  # the recorder's stop (s), None: not said
    end: float | None = None  # the bag's last message (s)


def load(path: str | Path) -> list[LineRecording]:
    """The lines recorded in the bag at ``path`` (none: an empty list)."""
    from .recording import _open, bag_path

    classes = {name: msg_class(t) for name, (_, t) in LINE_TOPICS.items()}
    string_cls = msg_class("std_msgs/msg/String")
    lines: dict[str, LineRecording] = {}
    try:
        with _open(bag_path(path)) as bag:
            wanted = [c for c in bag.connections if line_of(c.topic) or c.topic.endswith("/config")]
            if not any(line_of(c.topic) for c in wanted):
                return []
            last = -1
            for conn, ts, data in bag.messages(wanted):
                found = line_of(conn.topic)
                if found is None:
                    cell = conn.topic.strip("/").split("/")[0]
                    rec = lines.get(cell)
                    if rec is not None and rec.config_yaml is None:
                        rec.config_yaml = json.loads(
                            deserialize_message(bytes(data), string_cls).data
                        ).get("cell_yaml")
                    continue
                cell, name = found
                last = max(last, ts)
                rec = lines.setdefault(cell, LineRecording(cell))
                msg = deserialize_message(bytes(data), classes[name])
                {
                    "line/input_log": rec.inputs,
                    "line/episodes": rec.episodes,
                    "line/losses": rec.losses,
                    "line/snapshot": rec.snapshots,
                }[name].append(msg)
            if any(r.config_yaml is None for r in lines.values()):  # config after the line's topics
                for conn, _, data in bag.messages(
                    [c for c in wanted if c.topic.endswith("/config")]
                ):
                    rec = lines.get(conn.topic.strip("/").split("/")[0])
                    if rec is not None and rec.config_yaml is None:
                        rec.config_yaml = json.loads(
                            deserialize_message(bytes(data), string_cls).data
                        ).get("cell_yaml")
            notes = bag.custom
    except RecordingError:
        raise
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise RecordingError(f"{path}: cannot read the bag: {exc}", "unreadable") from None
    except Exception as exc:  # rosbags' reader errors (truncated, corrupt): as recording.load
        if type(exc).__module__.startswith("rosbags"):
            raise RecordingError(f"{path}: cannot read the bag: {exc}", "unreadable") from None
        raise
    stopped = notes.get("stopped_at_ns")
    pubs = notes.get("publications", {})
    for rec in lines.values():
        if isinstance(stopped, (int, float)) and not isinstance(stopped, bool):
            rec.stop = float(stopped) * 1e-9
        rec.end = last * 1e-9 if last >= 0 else None
        for name in LINE_OUTPUTS:
            ranges = pubs.get(f"/{rec.cell}/coordinator/{name}")
            recorded = rec.episodes if name == "line/episodes" else rec.losses
            if isinstance(ranges, list):
                try:
                    numbers = [n for a, b in ranges for n in range(int(a), int(b) + 1)]
                except (TypeError, ValueError):
                    continue
                if len(numbers) == len(recorded):
                    rec.publications[name.split("/")[1]] = numbers
    return list(lines.values())


@dataclass
class LineResult:
    cell: str
    inputs: int
    compared: dict[str, int]
    differences: list[str]
    #: output ("episodes", "losses") -> the first difference of that check ("" none)
    checks: dict[str, str] = field(default_factory=dict)
    origin: int = 0  # 0: the coordinator's start; else the snapshot's input index
    seconds: float = 0.0

    @property
    def ok(self) -> bool:
        return not self.differences

    def report(self) -> str:
        n = ", ".join(f"{v} {k}" for k, v in self.compared.items())
        since = f" from a snapshot after input #{self.origin}" if self.origin else ""
        if self.ok:
            return f"line {self.cell}: match ({self.inputs} inputs{since}; {n} compared)"
        return "\n".join(
            [
                f"line {self.cell}: DIFFERS ({self.inputs} inputs{since}; {n} compared)",
                *(f"  {d}" for d in self.differences[:MAX_SHOWN]),
            ]
        )


def _config(rec: LineRecording, config_file: str | Path | None, bag: Path) -> CellConfig:
    from ..core.safe_yaml import parse_document
    from ..core.secrets import redact

    try:
        if config_file is not None:
            return load_cell(config_file)
        if rec.config_yaml:
            source = f"{bag}:/{rec.cell}/<unit>/config"
            return parse_cell(redact(parse_document(rec.config_yaml, source)), source)
    except ConfigError as exc:
        raise RecordingError(
            f"{bag}: the configuration of line {rec.cell} is not valid: {exc}"
        ) from None
    raise RecordingError(
        f"{bag}: line {rec.cell} has no recorded configuration (no unit's config topic); give it with --config <cell.yaml>"
    )


@dataclass
class LineOrigin:
    """Where the line's replay starts: the coordinator's ``start`` (index 0) or a snapshot taken
    after input ``index``; ``published``: messages per output published before it."""

    index: int
    time: float  # s
    perf: Performance
    published: dict[str, int]


def _origin(rec: LineRecording, cell: CellConfig, log: list[Any]) -> tuple[LineOrigin, list[Any]]:
    """The earliest origin from which every later input is in the bag, and those inputs."""
    where = f"line {rec.cell}"
    present = [m.index for m in log]
    last = present[-1] if present else 0
    tail = last + 1  # the lowest index from which every input up to the last one is in the bag
    for k in range(len(present) - 1, -1, -1):
        if present[k] != tail - 1:
            break
        tail = present[k]
    if log and log[0].index == 1 and log[0].name == inputs.START and tail == 1:
        start = json.loads(log[0].args_json)
        if start.get("schema") != inputs.SCHEMA:
            raise RecordingError(
                f"{where}: input log schema {start.get('schema')!r}, this version reads {inputs.SCHEMA}"
            )
        perf = Performance(cell.line, cell.units, Ledger())
        if start.get("state"):
            perf.restore(start["state"])
        perf.ledger.restore(start.get("ledger") or {})
        origin = LineOrigin(
            0, line_msgs.ns_of(log[0].stamp) * 1e-9, perf, {"episodes": 0, "losses": 0}
        )
        return origin, log[1:]
    usable = [s for s in rec.snapshots if s.index + 1 >= tail]
    if usable:
        snap = min(usable, key=lambda s: (s.index, line_msgs.ns_of(s.stamp)))
        at = f"{where}: the snapshot after input #{snap.index}"
        try:
            doc = json.loads(snap.state_json)
        except ValueError as exc:
            raise RecordingError(f"{at} is not JSON: {exc}") from None
        schema = doc.get("schema") if isinstance(doc, dict) else None
        if schema != SNAPSHOT_SCHEMA:
            raise RecordingError(
                f"{at} has schema {schema!r}; this version reads {SNAPSHOT_SCHEMA}: replay it with the version that recorded it"
            )
        if doc.get("input_schema", inputs.SCHEMA) != inputs.SCHEMA:
            raise RecordingError(
                f"{at}: input log schema {doc.get('input_schema')!r}, this version reads {inputs.SCHEMA}"
            )
        published = doc.get("published")
        if not isinstance(published, dict) or not all(
            isinstance(published.get(k), int) and published[k] >= 0 for k in ("episodes", "losses")
        ):
            raise RecordingError(
                f"{at} does not say how many messages the coordinator had published"
            )
        try:
            perf = line_snapshot.restore(cell.line, cell.units, doc.get("line"))
        except SnapshotError as exc:
            raise RecordingError(f"{at}: {exc}") from None
        origin = LineOrigin(
            snap.index,
            line_msgs.ns_of(snap.stamp) * 1e-9,
            perf,
            {k: published[k] for k in ("episodes", "losses")},
        )
        return origin, [m for m in log if m.index > snap.index]
    if present and tail > present[0]:
        before = max(i for i in present if i < tail)
        raise RecordingError(
            f"{where}: the input log has a gap: inputs #{before + 1}..#{tail - 1} are missing (the recorder lost them) and no snapshot of the line's state follows it; record again",
            "missing_input",
        )
    first = present[0] if present else "none"
    raise RecordingError(
        f"{where}: the input log begins at #{first}, not at the coordinator's start, and the bag holds no snapshot of the line's state (/{rec.cell}/coordinator/line/snapshot) to start from: the coordinator runs a version that does not publish one; record it again with packml record",
        "missing_input",
    )


def replay(rec: LineRecording, cell: CellConfig) -> tuple[list[Any], list[Any], int, LineOrigin]:
    """The episode and losses messages the recorded inputs make again (after the origin), the
    inputs applied and the origin."""
    from .replay import check_log

    order = check_log(
        [(m.index, line_msgs.ns_of(m.stamp) * 1e-9, m.name) for m in rec.inputs], f"line {rec.cell}"
    )
    log = [rec.inputs[k] for k in order]
    origin, after = _origin(rec, cell, log)
    perf = origin.perf
    designs = {s: perf.design(s) for s in ("", *perf.order)}
    episodes: list[Any] = []
    losses: list[Any] = []
    for m in after:
        t = line_msgs.ns_of(m.stamp)
        try:
            fields = json.loads(m.args_json)
            inputs.apply(perf, m.name, t, fields)
        except (KeyError, ValueError, TypeError) as exc:
            raise RecordingError(
                f"line {rec.cell}: input #{m.index} ({m.name[:40]}) cannot be applied: {exc}"
            ) from None
        _, changed = perf.take()
        episodes += [line_msgs.episode_msg(episode_view(perf, e, t), cell.cell) for e in changed]
        if m.name == inputs.TICK and fields.get("publish"):
            losses += [
                line_msgs.losses_msg(v, cell.cell, t, designs) for v in published_windows(perf, t)
            ]
    return episodes, losses, len(after), origin


def _compare(
    topic: str,
    recorded: list[Any],
    pubs: list[int] | None,
    replayed: list[Any],
    offset: int,
    origin: LineOrigin,
    stop: float,
    out: list[str],
) -> int:
    """Compare one output to the end (see the module docstring); a difference goes to ``out``."""
    from .replay import diff

    def stamp(m: Any) -> float:
        return float(line_msgs.ns_of(m.stamp) * 1e-9)

    if pubs is not None:  # our recorder's publication numbers: exact
        pairs = [(k, p - 1 - offset) for k, p in enumerate(pubs) if p > offset]
    else:  # by content, from the first recorded message after the origin
        k0 = 0
        if origin.index:
            while k0 < len(recorded) and stamp(recorded[k0]) < origin.time:
                k0 += 1
        j0 = len(replayed)
        if k0 < len(recorded):
            j0 = next((j for j, m in enumerate(replayed) if not diff(m, recorded[k0], limit=1)), -1)
            if j0 < 0:
                out.append(
                    f"{topic}: recorded message #{k0} was not made by the replay ({len(replayed)} made)"
                )
                return 0
        pairs = [(k, j0 + k - k0) for k in range(k0, len(recorded))]
    for n, (k, j) in enumerate(pairs):
        if j >= len(replayed):
            out.append(
                f"{topic}: recorded message #{k} (t={stamp(recorded[k]):.3f}) was not made by the replay ({len(replayed)} made)"
            )
            return n
        fields = diff(replayed[j], recorded[k])
        if fields:
            shown = "; ".join(f"{p}: recorded {b!r}, replayed {a!r}" for p, a, b in fields[:4])
            out.append(f"{topic}: message #{k} differs from replayed #{j}: {shown}")
            return n
    end = pairs[-1][1] + 1 if pairs else 0
    for j in range(end, len(replayed)):
        if stamp(replayed[j]) < stop:
            out.append(
                f"{topic}: the replay made message #{j} (t={stamp(replayed[j]):.3f}) that the recording does not have, although the recorder was listening then"
            )
            return len(pairs)
        break
    return len(pairs)


def check(path: str | Path, config_file: str | Path | None = None) -> list[LineResult]:
    """Replay every line recorded in the bag (see the module docstring)."""
    import time

    results = []
    for rec in load(path):
        t0 = time.perf_counter()
        cell = _config(rec, config_file, Path(path))
        episodes, losses, n, origin = replay(rec, cell)
        stop = rec.stop
        if stop is None:  # another recorder's bag: up to its end, at least to the last input
            last_input = max(
                (line_msgs.ns_of(m.stamp) * 1e-9 for m in rec.inputs), default=origin.time
            )
            end = -math.inf if rec.end is None else rec.end - FOREIGN_MARGIN
            stop = max(end, math.nextafter(last_input, math.inf))
        compared: dict[str, int] = {}
        checks: dict[str, str] = {}
        differences: list[str] = []
        for name, recorded, replayed in (
            ("episodes", rec.episodes, episodes),
            ("losses", rec.losses, losses),
        ):
            problems: list[str] = []
            compared[name] = _compare(
                f"line/{name}",
                recorded,
                rec.publications.get(name),
                replayed,
                origin.published.get(name, 0),
                origin,
                stop,
                problems,
            )
            checks[name] = problems[0] if problems else ""
            differences += problems
        results.append(
            LineResult(
                rec.cell, n, compared, differences, checks, origin.index, time.perf_counter() - t0
            )
        )
    return results
