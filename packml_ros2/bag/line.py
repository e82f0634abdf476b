"""Record and replay a line's performance: the coordinator's ``line/input_log`` (its inputs) and
its outputs ``line/episodes`` and ``line/losses``.

``packml record <cell>`` records these topics beside the units' (:func:`topics`). ``packml
replay`` then also replays the line (:func:`check`): a fresh
:class:`~packml_ros2.core.line.performance.Performance` starts from the ``start`` input (the open
state and running windows the coordinator had restored), every input is applied again on its
recorded time through the same :func:`~packml_ros2.core.line.inputs.apply`, and every episode
change and every publication of losses is made again as the coordinator makes them
(:mod:`packml_ros2.line_msgs`) and compared with the recorded messages on decoded values. The
input log must be complete (indices 1..n from ``start``): the coordinator keeps 5000 inputs for
a recorder that joins late. Recorded messages published before the recorder joined (the latched
history) are matched by content: the first recorded message of a topic is looked for in the
replayed stream, and from there the streams are compared one to one.
"""

from __future__ import annotations

import itertools
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rclpy.serialization import deserialize_message

from .. import line_msgs
from ..core import ConfigError, load_cell, parse_cell
from ..core.config import CellConfig
from ..core.line import inputs
from ..core.line.ledger import Ledger
from ..core.line.line import episode_view, published_windows
from ..core.line.performance import Performance
from .recording import RecordingError
from .topics import msg_class

#: topic (relative to ``/<cell>/coordinator``) -> (kind in topics.PUBLISHER_QOS, ROS type)
LINE_TOPICS: dict[str, tuple[str, str]] = {
    "line/input_log": ("line_input_log", "packml_interfaces/msg/UnitInput"),
    "line/episodes": ("line_episodes", "packml_interfaces/msg/LineEpisode"),
    "line/losses": ("line_losses", "packml_interfaces/msg/LineLosses"),
}
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


@dataclass
class LineRecording:
    cell: str
    inputs: list[Any] = field(default_factory=list)  # UnitInput messages
    episodes: list[Any] = field(default_factory=list)
    losses: list[Any] = field(default_factory=list)
    config_yaml: str | None = None


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
            for conn, _, data in bag.messages(wanted):
                found = line_of(conn.topic)
                if found is None:
                    cell = conn.topic.strip("/").split("/")[0]
                    rec = lines.get(cell)
                    if rec is not None and rec.config_yaml is None:
                        rec.config_yaml = json.loads(deserialize_message(bytes(data), string_cls).data).get("cell_yaml")  # fmt: skip
                    continue
                cell, name = found
                rec = lines.setdefault(cell, LineRecording(cell))
                msg = deserialize_message(bytes(data), classes[name])
                {"line/input_log": rec.inputs, "line/episodes": rec.episodes, "line/losses": rec.losses}[name].append(msg)  # fmt: skip
            if any(r.config_yaml is None for r in lines.values()):  # config after the line's topics
                for conn, _, data in bag.messages([c for c in wanted if c.topic.endswith("/config")]):  # fmt: skip
                    rec = lines.get(conn.topic.strip("/").split("/")[0])
                    if rec is not None and rec.config_yaml is None:
                        rec.config_yaml = json.loads(deserialize_message(bytes(data), string_cls).data).get("cell_yaml")  # fmt: skip
    except RecordingError:
        raise
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise RecordingError(f"{path}: cannot read the bag: {exc}") from None
    except Exception as exc:  # rosbags' reader errors (truncated, corrupt): as recording.load
        if type(exc).__module__.startswith("rosbags"):
            raise RecordingError(f"{path}: cannot read the bag: {exc}") from None
        raise
    return list(lines.values())


@dataclass
class LineResult:
    cell: str
    inputs: int
    compared: dict[str, int]
    differences: list[str]

    @property
    def ok(self) -> bool:
        return not self.differences

    def report(self) -> str:
        n = ", ".join(f"{v} {k}" for k, v in self.compared.items())
        if self.ok:
            return f"line {self.cell}: match ({self.inputs} inputs; {n} compared)"
        return "\n".join([f"line {self.cell}: DIFFERS ({self.inputs} inputs; {n} compared)",
                          *(f"  {d}" for d in self.differences[:MAX_SHOWN])])  # fmt: skip


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
        raise RecordingError(f"{bag}: the configuration of line {rec.cell} is not valid: {exc}") from None  # fmt: skip
    raise RecordingError(f"{bag}: line {rec.cell} has no recorded configuration (no unit's config topic); give it with --config <cell.yaml>")  # fmt: skip


def replay(rec: LineRecording, cell: CellConfig) -> tuple[list[Any], list[Any], int]:
    """The episode and losses messages the recorded inputs make again, and the inputs applied."""
    log = sorted(rec.inputs, key=lambda m: m.index)
    if not log or log[0].index != 1 or log[0].name != inputs.START:
        first = log[0].index if log else "none"
        raise RecordingError(f"line {rec.cell}: the input log begins at #{first}, not at the coordinator's start: record from the coordinator's start (it keeps 5000 inputs)")  # fmt: skip
    gaps = [b.index for a, b in itertools.pairwise(log) if b.index != a.index + 1]
    if gaps:
        raise RecordingError(f"line {rec.cell}: the input log has a gap before #{gaps[0]}")
    start = json.loads(log[0].args_json)
    if start.get("schema") != inputs.SCHEMA:
        raise RecordingError(f"line {rec.cell}: input log schema {start.get('schema')!r}, this version reads {inputs.SCHEMA}")  # fmt: skip
    perf = Performance(cell.line, cell.units, Ledger())
    if start.get("state"):
        perf.restore(start["state"])
    perf.ledger.restore(start.get("ledger") or {})
    designs = {s: perf.design(s) for s in ("", *perf.order)}
    episodes: list[Any] = []
    losses: list[Any] = []
    for m in log[1:]:
        t = line_msgs.ns_of(m.stamp)
        fields = json.loads(m.args_json)
        try:
            inputs.apply(perf, m.name, t, fields)
        except (KeyError, ValueError, TypeError) as exc:
            raise RecordingError(f"line {rec.cell}: input #{m.index} ({m.name[:40]}) cannot be applied: {exc}") from None  # fmt: skip
        _, changed = perf.take()
        episodes += [line_msgs.episode_msg(episode_view(perf, e, t), cell.cell) for e in changed]
        if m.name == inputs.TICK and fields.get("publish"):
            losses += [line_msgs.losses_msg(v, cell.cell, t, designs) for v in published_windows(perf, t)]  # fmt: skip
    return episodes, losses, len(log)


def _compare(topic: str, recorded: list[Any], replayed: list[Any], out: list[str]) -> int:
    from .replay import diff

    if not recorded:
        return 0
    start = next((i for i, m in enumerate(replayed) if not diff(m, recorded[0], limit=1)), None)
    if start is None:
        out.append(f"{topic}: recorded message #0 was not made by the replay ({len(replayed)} made)")  # fmt: skip
        return 0
    for i, m in enumerate(recorded):
        j = start + i
        if j >= len(replayed):
            out.append(f"{topic}: recorded message #{i} was not made by the replay")
            return i
        fields = diff(replayed[j], m)
        if fields:
            shown = "; ".join(f"{p}: recorded {b!r}, replayed {a!r}" for p, a, b in fields[:4])
            out.append(f"{topic}: message #{i} differs: {shown}")
            return i
    return len(recorded)


def check(path: str | Path, config_file: str | Path | None = None) -> list[LineResult]:
    """Replay every line recorded in the bag (see the module docstring)."""
    results = []
    for rec in load(path):
        cell = _config(rec, config_file, Path(path))
        episodes, losses, n = replay(rec, cell)
        problems: list[str] = []
        compared = {
            "episodes": _compare("line/episodes", rec.episodes, episodes, problems),
            "losses": _compare("line/losses", rec.losses, losses, problems),
        }
        results.append(LineResult(rec.cell, n, compared, problems))
    return results
