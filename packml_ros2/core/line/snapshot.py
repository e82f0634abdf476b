"""The line's state as a versioned document, as :mod:`packml_ros2.core.snapshot` is a unit's: what a
replay needs to continue the line's performance exactly from between two inputs — the open state
(:meth:`~.performance.Performance.document`: trackers, the line, the open episode), what that
document leaves to the store (each tracker's transitions waiting for a first status and a status
ahead of its transitions) and the running windows (:meth:`~.ledger.Ledger.base`: lifetime, since
reset, the open shifts, the last hour).

The coordinator publishes one on ``<cell>/coordinator/line/snapshot`` when a recorder joins:
a recording of a line that has logged more inputs than its input log keeps (5000) replays from it.

    document = capture(perf, now)          # JSON values only
    perf = restore(line_config, units, document)

Schema 1; :func:`restore` refuses another schema or a document that does not fit
(:class:`SnapshotError`: a reason, nothing built).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict
from typing import Any

from ..snapshot import SnapshotError
from .config import LineConfig
from .ledger import Ledger
from .performance import Performance, StatusSnap, TransitionSnap, UnitLike

SCHEMA = 1


def capture(perf: Performance, now: int) -> dict[str, Any]:
    """The state of ``perf`` between two inputs at ``now`` (line clock, ns), as JSON values."""
    cal = perf.calendar
    keep = [i.key for i in (cal.instance_at(now), cal.previous(now)) if i]
    waiting = {
        name: {
            "pending": [asdict(t) for t in tr.pending],
            "ahead": None if tr.ahead is None else [asdict(tr.ahead[0]), tr.ahead[1]],
        }
        for name, tr in perf.trackers.items()
        if tr.pending or tr.ahead is not None
    }
    return {
        "schema": SCHEMA,
        "state": perf.document(),
        "waiting": waiting,
        "ledger": perf.ledger.base(keep),
    }


def restore(config: LineConfig, units: Mapping[str, UnitLike], document: Any) -> Performance:
    """A :class:`Performance` in the state ``document`` describes (no history of facts)."""
    schema = document.get("schema") if isinstance(document, Mapping) else None
    if schema != SCHEMA:
        newer = isinstance(schema, int) and schema > SCHEMA
        raise SnapshotError(
            f"line snapshot schema {schema!r}: this version reads schema {SCHEMA}"
            + (
                " (the snapshot is newer: replay it with the version that recorded it)"
                if newer
                else ""
            )
        )
    perf = Performance(config, units, Ledger())
    try:
        state = document["state"]
        unknown = set(state.get("trackers", {})) - set(perf.trackers)
        if unknown:
            raise SnapshotError(
                f"the line snapshot has units {sorted(unknown)} the configuration has not"
            )
        perf.restore(state)
        for name, w in document.get("waiting", {}).items():
            tr = perf.trackers[name]
            tr.pending = [TransitionSnap(**t) for t in w["pending"]]
            ahead = w["ahead"]
            tr.ahead = None if ahead is None else (StatusSnap(**ahead[0]), int(ahead[1]))
        perf.ledger.restore(document["ledger"])
    except SnapshotError:
        raise
    except (TypeError, ValueError, KeyError, IndexError, AttributeError) as exc:
        raise SnapshotError(
            f"the line snapshot cannot be restored: {type(exc).__name__}: {exc}"
        ) from None
    return perf


__all__ = ["SCHEMA", "capture", "restore"]
