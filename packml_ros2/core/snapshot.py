"""A unit's engine state as a versioned document: everything that decides what the engine does
next and what it publishes — the machine, every part (alarms with their history and first-outs,
times, counters, EMs, interlocks, stop reason), the deadlines and what the last publications
showed. A recording that starts late begins with one (the unit node publishes it when a recorder
joins), and replay starts from it instead of from the unit's start.

    document = capture(unit)                       # JSON values only
    unit = restore(config, clock, document)        # the same engine, on another clock

:func:`restore` builds a unit that is indistinguishable from the captured one: the same inputs
at the same times give the same outputs. What is not in the document is listed in
:data:`NOT_STATE` with the reason (configuration, compiled rules, caches); a test walks every
attribute of a unit and its parts and fails on one that is neither captured nor listed there.

Schema 1 is this module's; :func:`restore` refuses a document of another schema or one that does
not fit the configuration (:class:`SnapshotError`: a reason, nothing built).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import fields
from typing import TYPE_CHECKING, Any

from . import inputlog
from .alarms import AlarmEvent
from .deadlines import Due
from .equipment import EquipmentModule
from .numbers import NUM_MODES, NUM_STATES, State
from .outputs import Outputs

if TYPE_CHECKING:
    from .config import UnitConfig
    from .durable import StoreLike
    from .unit import Unit

SCHEMA = 1

#: Attributes of a unit and its parts that a snapshot leaves out, and why (see the module doc).
NOT_STATE: Mapping[str, str] = {
    "Unit.config": "the configuration: given to restore()",
    "Unit.rules": "compiled from the configuration",
    "Unit._clock": "given to restore()",
    "Unit.store": "given to restore()",
    "Unit._durable": "the store's link to the parts (write-ahead journal)",
    "Unit.on_input": "the input log's sink: set by whoever drives the unit",
    "Unit.restored": "the admin data restored at the unit's start (its start record has it)",
    "Unit.mode_def": "the configuration of Unit.mode",
    "Unit._accepted": "compiled from the configuration",
    "Unit._accepted_mode": "compiled from the configuration for Unit.mode",
    "Unit._sc": "compiled from the configuration",
    "Unit._timed": "from the configuration",
    "Unit._handlers": "the deadline handlers (methods)",
    "Unit._frame": "what closes an input's frame (the unit's _leave)",
    "Unit._out": "the output queue: empty between inputs (drained)",
    "Unit._internal": "commands queued inside one input: empty between inputs",
    "Unit._valid_cache": "a cache",
    "Unit._restart_detail": "read only while the unit starts",
    "Unit.legacy_interlock_source": "set by the replay from the recording's input log schema",
    "AlarmManager.defs": "the configuration",
    "AlarmManager.reactions": "the configuration",
    "AlarmManager.alarm_capacity": "the configuration",
    "AlarmManager.warning_capacity": "the configuration",
    "AlarmManager.history_capacity": "the configuration",
    "AlarmManager.alert": "the unit's Alert (captured once)",
    "AlarmManager.changed": "what the persistence journal has not written yet",
    "AlarmManager._saved": "a cache",
    "Counters.capacity": "the configuration",
    "Counters._snapshots": "a cache",
    "Equipment.alert": "the unit's Alert (captured once)",
    "Equipment.active": "counted from the EMs",
    "Equipment._owing": "derived from the EMs",
    "Interlocks.alert": "the unit's Alert (captured once)",
    "StopReasons.planned_ids": "the configuration",
    "StopReasons.planned_reason": "derived from the reason",
    "ModeStateTimes._base": "derived from the mode",
    "Deadlines.next_due": "derived from the heap",
    "Publication._admin_key_of": "the unit's method",
    "Publication._status_key_of": "the unit's method",
    "Publication._alarms": "the unit's AlarmManager",
    "Publication._deadlines": "the unit's Deadlines",
    "Publication._emit": "the unit's queue",
    "Recipes.book": "the configuration",
}


class SnapshotError(ValueError):
    """A snapshot that cannot be restored (the message says why)."""


def _time(value: float) -> float | None:
    return value if math.isfinite(value) else None


def _sparse(values: list[float]) -> dict[str, float]:
    return {str(i): v for i, v in enumerate(values) if v}


def _dense(data: Mapping[str, Any], size: int) -> list[float]:
    out = [0.0] * size
    for key, value in data.items():
        i = int(key)
        if not 0 <= i < size:
            raise SnapshotError(f"time index {i} outside 0..{size - 1}")
        out[i] = float(value)
    return out


# -- capture ---------------------------------------------------------------------------------------
def capture(unit: Unit) -> dict[str, Any]:
    """The engine state of ``unit`` between two inputs, as JSON values."""
    if unit._out or unit._internal:
        raise RuntimeError("a snapshot is taken between inputs, with the outputs drained")
    alarms, eq, times, pub, dl = (
        unit.alarms,
        unit.equipment,
        unit.times,
        unit.publication,
        unit.deadlines,
    )
    events: list[dict[str, Any]] = []
    index: dict[int, int] = {}

    def ref(ev: AlarmEvent | None) -> int | None:
        if ev is None:
            return None
        i = index.get(id(ev))
        if i is None:
            i = index[id(ev)] = len(events)
            events.append(ev.to_dict())
        return i

    document: dict[str, Any] = {
        "schema": SCHEMA,
        "unit": unit.config.name,
        "time": unit._t,
        "advance_to": unit._advance_to,
        "machine": {
            "state": int(unit.state),
            "mode": unit.mode,
            "sequence": unit.sequence,
            "entered_at": unit.entered_at,
            "mode_requested": unit.mode_requested,
            "mode_change_in_process": unit.mode_change_in_process,
            "mode_source": unit._mode_source,
            "mode_change_not_allowed_until": _time(unit.mode_change_not_allowed_until),
            "sc_refused": unit._sc_refused,
            "step_winner": list(unit._step_winner) if unit._step_winner else None,
            "rev": unit._rev,
            "strays": sorted(unit._strays),
        },
        "command": {
            "remote_enabled": unit.remote_enabled,
            "cntrl_cmd": unit.cntrl_cmd,
            "unit_mode": unit.command_unit_mode,
            "mach_speed": unit.mach_speed,
            "parameters": [inputlog.descriptor_to_dict(p) for p in unit.parameters],
            "products": [inputlog.product_to_dict(p) for p in unit.products],
            "remote_commands": [[n, c, v] for n, (c, v) in unit.remote_commands.items()],
        },
        "alert": unit.alert.bits,
        "stats": {f.name: getattr(unit.stats, f.name) for f in fields(unit.stats)},
        "alarms": {
            "current": [ref(ev) for ev in alarms.current.values()],
            "history": [ref(ev) for ev in alarms.history],
            "history_dropped": alarms.history_dropped,
            "first_out": ref(alarms.first_out),
            "first_out_by_category": [
                [c, ref(ev)] for c, ev in alarms.first_out_by_category.items()
            ],
            "first_out_by_em": [[em, ref(ev)] for em, ev in alarms.first_out_by_em.items()],
            "version": alarms.version,
            "blocking_version": alarms.blocking_version,
            "serial": alarms.serial,
        },
        "stops": {"reason": ref(unit.stops.reason), "armed": unit.stops.armed},
        "times": {
            "mode_current": _sparse(times.mode_current),
            "mode_cumulative": _sparse(times.mode_cumulative),
            "state_current": _sparse(times.state_current),
            "state_cumulative": _sparse(times.state_cumulative),
            "acc_time_since_reset": times.acc_time_since_reset,
            "planned_stop": times.planned_stop,
            "mode": times._mode,
            "state": times._state,
            "planned": times._planned,
            "modes_used": sorted(times.modes_used),
            "since": times._since,
            "mode_since": times._mode_since,
            "resets": times.resets,
        },
        "counters": {
            "version": unit.counters.version,
            "values": {
                k: [[c.count, c.acc_count] for c in a] for k, a in unit.counters.arrays.items()
            },
        },
        "equipment": {
            "modules": [
                {f.name: getattr(em, f.name) for f in fields(EquipmentModule)}
                for em in eq.modules.values()
            ],
            "state": int(eq.state),
            "sequence": eq.sequence,
            "current": list(eq.current),
            "pending": sorted(eq.pending),
            "aggregating": eq.aggregating,
            "version": eq.version,
            "roster_version": eq.roster_version,
        },
        "interlocks": {
            "active": [
                [k, reason, stop_id] for k, (reason, stop_id) in unit.interlocks.active.items()
            ],
            "suspended": unit.interlocks.suspended,
            "attempt": list(unit.interlocks.attempt),
            "busy": unit.interlocks.busy,
            "released": unit.interlocks.released,
        },
        "deadlines": {
            "heap": [
                [when, order, kind.name.lower(), _plain(data)]
                for when, order, kind, data in dl.heap
            ],
            "counter": dl._counter,
        },
        "recipes": unit.recipes.to_dict(),
        "publication": {
            "status_key": list(pub.status_key),
            "status_due": pub.status_due,
            "admin_key": list(pub.admin_key),
            "admin_due": pub.admin_due,
            "alarms_seen": pub.alarms_seen,
        },
    }
    document["events"] = events
    return document


def _plain(data: Any) -> Any:
    """A deadline's data as JSON: (State, sequence) pairs become lists."""
    if isinstance(data, tuple):
        return [int(x) for x in data]
    return data


#: Deadline data from JSON, by kind (the handlers' argument types).
_DEADLINE_DATA: Mapping[Due, Callable[[Any], Any]] = {
    Due.TIMEOUT: lambda d: (State(int(d[0])), int(d[1])),
    Due.DWELL: lambda d: (State(int(d[0])), int(d[1])),
    Due.MODE_TIMEOUT: int,
    Due.SAVE: float,
    Due.ADMIN: float,
    Due.RECIPE_TIMEOUT: int,
    Due.STATUS: lambda d: None,
    Due.LAMP_OFF: lambda d: None,
    Due.ADMIN_CHANGE: lambda d: None,
}


# -- restore ---------------------------------------------------------------------------------------
def restore(
    config: UnitConfig,
    clock: Callable[[], float],
    document: Mapping[str, Any],
    store: StoreLike | None = None,
) -> Unit:
    """A unit in the state ``document`` describes, on ``clock``; its outputs drained (none
    pending). :class:`SnapshotError` when the document cannot be restored."""
    from .unit import Unit

    schema = document.get("schema") if isinstance(document, Mapping) else None
    if schema != SCHEMA:
        newer = isinstance(schema, int) and schema > SCHEMA
        raise SnapshotError(
            f"snapshot schema {schema!r}: this version reads schema {SCHEMA}"
            + (
                " (the snapshot is newer: replay it with the version that recorded it)"
                if newer
                else ""
            )
        )
    if document.get("unit") != config.name:
        raise SnapshotError(
            f"the snapshot is of unit {document.get('unit')!r}, not {config.name!r}"
        )
    unit = Unit(config, clock=clock, store=store)  # type: ignore[arg-type]
    unit.drain()  # the start-up outputs of this new unit: the snapshot's replace them
    try:
        _restore(unit, document)
    except SnapshotError:
        raise
    except (TypeError, ValueError, KeyError, IndexError, AttributeError) as exc:
        raise SnapshotError(
            f"the snapshot cannot be restored: {type(exc).__name__}: {exc}"
        ) from None
    return unit


def _restore(unit: Unit, d: Mapping[str, Any]) -> None:
    config = unit.config
    events = [AlarmEvent.from_dict(e) for e in d["events"]]

    def ev(i: Any) -> AlarmEvent | None:
        return None if i is None else events[int(i)]

    def evs(items: Any) -> list[AlarmEvent]:
        return [events[int(i)] for i in items]

    unit._t = float(d["time"])
    unit._advance_to = float(d["advance_to"])
    m = d["machine"]
    unit.state = State(int(m["state"]))
    mode = int(m["mode"])
    if mode not in config.modes:
        raise SnapshotError(f"the snapshot's mode {mode} is not configured")
    unit.mode, unit.mode_def = mode, config.modes[mode]
    unit._accepted_mode = unit._accepted[mode]
    unit.sequence = int(m["sequence"])
    unit.entered_at = float(m["entered_at"])
    unit.mode_requested = int(m["mode_requested"])
    unit.mode_change_in_process = bool(m["mode_change_in_process"])
    unit._mode_source = str(m["mode_source"])
    until = m["mode_change_not_allowed_until"]
    unit.mode_change_not_allowed_until = -math.inf if until is None else float(until)
    unit._sc_refused = int(m["sc_refused"])
    winner = m["step_winner"]
    unit._step_winner = None if winner is None else (int(winner[0]), str(winner[1]))
    unit._rev = int(m["rev"])
    unit._strays = {str(s) for s in m["strays"]}

    c = d["command"]
    unit.remote_enabled = bool(c["remote_enabled"])
    unit.cntrl_cmd = int(c["cntrl_cmd"])
    unit.command_unit_mode = int(c["unit_mode"])
    unit.mach_speed = float(c["mach_speed"])
    unit.parameters = [inputlog.descriptor_from_dict(p) for p in c["parameters"]]
    unit.products = [inputlog.product_from_dict(p) for p in c["products"]]
    unit.remote_commands = {int(n): (int(cmd), int(v)) for n, cmd, v in c["remote_commands"]}
    unit.alert.bits = int(d["alert"])
    for name, value in d["stats"].items():
        if hasattr(unit.stats, name):
            setattr(unit.stats, name, int(value))

    a, alarms = d["alarms"], unit.alarms
    alarms.current = {e.key: e for e in evs(a["current"])}
    alarms.history.clear()
    history = evs(a["history"])
    if len(history) > (alarms.history.maxlen or 0):
        raise SnapshotError(
            f"{len(history)} history entries; the unit keeps {alarms.history.maxlen}"
        )
    alarms.history.extend(history)
    alarms.history_dropped = int(a["history_dropped"])
    alarms.first_out = ev(a["first_out"])
    alarms.first_out_by_category = {int(k): events[int(i)] for k, i in a["first_out_by_category"]}
    alarms.first_out_by_em = {str(k): events[int(i)] for k, i in a["first_out_by_em"]}
    alarms.version = int(a["version"])
    alarms.blocking_version = int(a["blocking_version"])
    alarms.serial = int(a["serial"])
    alarms.__dict__.pop("_saved", None)
    if alarms.changed is not None:
        alarms.take_changed()  # (the journal's tracking: nothing is owed to the store)
    unit.stops.set(ev(d["stops"]["reason"]))
    unit.stops.armed = bool(d["stops"]["armed"])

    t, times = d["times"], unit.times
    times.mode_current = _dense(t["mode_current"], NUM_MODES)
    times.mode_cumulative = _dense(t["mode_cumulative"], NUM_MODES)
    times.state_current = _dense(t["state_current"], NUM_MODES * NUM_STATES)
    times.state_cumulative = _dense(t["state_cumulative"], NUM_MODES * NUM_STATES)
    times.acc_time_since_reset = float(t["acc_time_since_reset"])
    times.planned_stop = float(t["planned_stop"])
    times._mode = int(t["mode"])
    times._base = times._mode * NUM_STATES
    times._state = int(t["state"])
    times._planned = bool(t["planned"])
    times.modes_used = {int(x) for x in t["modes_used"]}
    times._since = float(t["since"])
    # (snapshots before the mode figures had a clock of their own held them as of "since")
    times._mode_since = float(t.get("mode_since", t["since"]))
    times.resets = int(t["resets"])
    if not 0 <= times._mode < NUM_MODES or not 0 <= times._state < NUM_STATES:
        raise SnapshotError(f"times of mode {times._mode} state {times._state}: out of range")

    k, counters = d["counters"], unit.counters
    counters.version = int(k["version"])
    for kind, values in k["values"].items():
        array = counters.arrays[kind]
        if len(values) != len(array):
            raise SnapshotError(
                f"{len(values)} {kind} counters; the configuration has {len(array)}"
            )
        for counter, (count, acc) in zip(array, values, strict=True):
            counter.count, counter.acc_count = int(count), int(acc)
    counters.__dict__.pop("_snapshots", None)

    e, eq = d["equipment"], unit.equipment
    eq.modules = {}
    for em in e["modules"]:
        last = em["last_report"]
        eq.modules[str(em["name"])] = EquipmentModule(
            **{**em, "last_report": None if last is None else (int(last[0]), int(last[1]))}
        )
    bits, versions = unit.alert.bits, (e["version"], e["roster_version"])
    eq.changed_roster()  # (counts the active EMs and who owes State Complete)
    unit.alert.bits = bits
    eq.version, eq.roster_version = int(versions[0]), int(versions[1])
    eq.state = State(int(e["state"]))
    eq.sequence = int(e["sequence"])
    eq.current = (State(int(e["current"][0])), int(e["current"][1]))
    eq.pending = {str(x) for x in e["pending"]}
    eq.aggregating = bool(e["aggregating"])

    i, interlocks = d["interlocks"], unit.interlocks
    interlocks.active = {str(key): (str(reason), int(stop)) for key, reason, stop in i["active"]}
    interlocks.suspended = bool(i["suspended"])
    interlocks.attempt = (int(i["attempt"][0]), int(i["attempt"][1]))
    interlocks.busy = bool(i["busy"])
    interlocks.released = str(i.get("released", ""))

    dl = unit.deadlines
    heap = [
        (float(w), int(o), Due[kind.upper()], _DEADLINE_DATA[Due[kind.upper()]](data))
        for w, o, kind, data in d["deadlines"]["heap"]
    ]
    if any(heap[(j - 1) // 2][:2] > heap[j][:2] for j in range(1, len(heap))):
        raise SnapshotError("the deadlines are not a heap")
    dl.heap = heap
    dl.next_due = heap[0][0] if heap else math.inf
    dl._counter = int(d["deadlines"]["counter"])

    if "recipes" in d:  # (snapshots before recipes: none current, no changeover)
        unit.recipes.restore(d["recipes"])

    p, pub = d["publication"], unit.publication
    pub.status_key = tuple(int(x) for x in p["status_key"])
    pub.status_due = bool(p["status_due"])
    pub.admin_key = tuple(int(x) for x in p["admin_key"])
    pub.admin_due = bool(p["admin_due"])
    pub.alarms_seen = int(p["alarms_seen"])

    unit._valid_cache.clear()
    unit._out = Outputs()
    unit._internal = []
    unit.restored = None
    durable = unit._durable
    if durable is not None:  # nothing to journal: the store has what the snapshot has
        durable._written = durable._state(unit.sequence, unit.mode, unit.mach_speed)


__all__ = ["NOT_STATE", "SCHEMA", "SnapshotError", "capture", "restore"]
