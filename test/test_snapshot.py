"""Issue 16: a unit's engine state as a snapshot (core/snapshot.py), from which replay starts when
a recording began late.

A unit restored from a snapshot (through JSON) equals the captured one attribute by attribute
(every attribute of the unit and its parts is either captured or named in snapshot.NOT_STATE),
and given the same inputs at the same times afterwards it publishes the same messages — after
random campaigns of every kind of input, and after a million inputs.
"""

from __future__ import annotations

import json
import math
import random
import time
from collections import deque
from collections.abc import Callable
from dataclasses import fields, is_dataclass
from enum import Enum
from typing import Any

import pytest
from rclpy.serialization import serialize_message

from packml_ros2.bag.cdr import canonical
from packml_ros2.core import Cmd, State, Unit, parse_cell, snapshot
from packml_ros2.core.alarms import AlarmEvent
from packml_ros2.core.config import Descriptor, Product
from packml_ros2.driver import FrozenClock, UnitDriver
from test.core.test_stateful import UNIT as STATEFUL_UNIT

#: The unit of the stateful engine test (modes, EMs of every lost reaction, alarms of every
#: reaction, timeouts, dwell), with interlocks, registration, a remote interface, a short history.
CELL = {
    "cell": "snap_cell",
    "units": {
        "u": {
            **STATEFUL_UNIT,
            "persistence": False,
            "admin_period": 1.0,
            "interlock_reaction": "suspend",
            "allow_registration": True,
            "remote_interfaces": [{"number": 1, "name": "mes"}],
            "sizes": {"history": 16},
        }
    },
}
CONFIG = parse_cell(CELL).units["u"]
EMS = ("a", "b", "c", "d", "x")
SOURCES = ("operator", "remote:mes", "em:a", "")
T0 = 1_750_000_000.0


# -- the engine driven like the node (the same UnitDriver), its messages collected --------------------
class Driven:
    def __init__(self, unit: Unit, clock: FrozenClock, now: list[float]) -> None:
        self.unit, self.clock, self.now = unit, clock, now
        self.out: list[tuple[str, bytes]] = []
        self.driver = UnitDriver(unit, clock, self._emit)

    @classmethod
    def fresh(cls, store: Any = None) -> Driven:
        now = [T0]
        clock = FrozenClock(lambda: now[0])
        return cls(Unit(CONFIG, clock=clock, store=store), clock, now)

    @classmethod
    def restored(cls, document: dict[str, Any]) -> Driven:
        doc = json.loads(json.dumps(document))  # what a bag carries: JSON text
        now = [float(doc["time"])]
        clock = FrozenClock(lambda: now[0])
        return cls(snapshot.restore(CONFIG, clock, doc), clock, now)

    def _emit(self, topic: str, msg: Any) -> None:
        if topic != "log":
            self.out.append((topic, canonical(bytes(serialize_message(msg)), type(msg))))

    def apply(self, step: tuple[float, str, tuple[Any, ...]]) -> None:
        dt, method, args = step
        self.now[0] += dt
        self.driver.catch_up(self.now[0])
        if method != "wait":
            self.driver.call(self.now[0], getattr(self.unit, method), *args)


def random_inputs(
    rng: random.Random, n: int, unit: Unit
) -> list[tuple[float, str, tuple[Any, ...]]]:
    """``n`` inputs of every kind (mostly plausible, some not), with the time passing between."""
    steps: list[tuple[float, str, tuple[Any, ...]]] = []
    for _ in range(n):
        dt = rng.choice((0.0, 0.0, 0.01, 0.05, 0.3, 1.0, 3.5))
        r = rng.random()
        if r < 0.3:  # State Complete of what the unit is in now (or was: stale)
            eq = unit.equipment
            seq = eq.sequence - (1 if rng.random() < 0.1 else 0)
            step = ("em_complete", (rng.choice(EMS[:4]), int(eq.state), seq))
        elif r < 0.45:
            step = ("command", (rng.choice(list(Cmd)[1:]), rng.choice(SOURCES)))
        elif r < 0.5:
            step = ("set_mode", (rng.choice((1, 2, 3, 4, "MANUAL", 9)), rng.choice(SOURCES)))
        elif r < 0.55:
            step = ("em_seen", (rng.choice(EMS), rng.random() < 0.5))
        elif r < 0.58:
            step = ("em_lost", (rng.choice(EMS), "no report"))
        elif r < 0.63:
            step = (
                "em_interlock",
                (rng.choice(EMS[:4]), rng.random() < 0.3, rng.random() < 0.2, rng.randrange(4)),
            )
        elif r < 0.7:
            step = (
                "em_count",
                (
                    rng.choice(EMS[:3]),
                    rng.choice(("consumed", "processed", "defective")),
                    rng.randrange(3),
                    rng.randrange(4),
                ),
            )
        elif r < 0.72:
            step = ("set_em_active", (rng.choice(EMS), rng.random() < 0.5, "operator"))
        elif r < 0.8:
            step = (
                "set_alarm",
                (
                    rng.choice((101, 102, 103, 104, 105, 106, 777)),
                    0,
                    rng.random() < 0.6,
                    "operator",
                    rng.choice(("", "a")),
                    None,
                    rng.choice((-1, 5)),
                    rng.choice(("", "made up")),
                ),
            )
        elif r < 0.83:
            step = ("ack_alarms", (rng.choice((None, 101, 102)), 0, "operator"))
        elif r < 0.86:
            step = ("reset_alarms", (rng.random() < 0.3, "operator"))
        elif r < 0.87:
            step = ("reset_times", (rng.random() < 0.5, "operator"))
        elif r < 0.88:
            step = ("reset_counters", ("operator",))
        elif r < 0.9:
            step = ("set_mach_speed", (rng.choice((0.0, 12.5, 60.0, -1.0)), "operator"))
        elif r < 0.91:
            step = (
                "set_parameters",
                ([Descriptor(rng.randrange(3), "p", "mm", rng.random())], "operator"),
            )
        elif r < 0.92:
            step = ("set_product", ([Product(rng.randrange(3))], "operator"))
        elif r < 0.93:
            step = ("set_remote_enabled", (rng.random() < 0.5,))
        elif r < 0.96:
            step = (
                "set_interlock",
                (rng.random() < 0.5, rng.choice(("starved", "blocked")), "remote:line"),
            )
        elif r < 0.965:
            step = ("shutdown", ("SIGINT",))  # (recorded; the engine goes on in a test)
        else:
            step = ("wait", ())
        steps.append((dt, step[0], step[1]))
    return steps  # fmt: skip


# -- the state of a unit, every attribute of it and of its parts ------------------------------------------
def state_of(unit: Unit) -> Any:
    """Every attribute of ``unit`` and its parts that snapshot.NOT_STATE does not name, as plain
    values (AlarmEvents by value and by which attributes share one); fails on a callable that
    is not named there (a new part's link would otherwise hide)."""
    shared: dict[int, int] = {}

    def walk(x: Any, where: str) -> Any:
        if x is None or isinstance(x, (bool, str)):
            return x
        if isinstance(x, Enum):
            return int(x.value)
        if isinstance(x, int):
            return x
        if isinstance(x, float):
            return "nan" if math.isnan(x) else x
        if isinstance(x, AlarmEvent):
            if id(x) in shared:
                return ("same event as", shared[id(x)])
            shared[id(x)] = len(shared)
            return ("event", walk(x.to_dict(), where))
        if is_dataclass(x) and type(x).__dataclass_params__.frozen:  # type: ignore[attr-defined]
            return (type(x).__name__, [walk(getattr(x, f.name), where) for f in fields(x)])
        if isinstance(x, (list, tuple, deque)):
            return [walk(v, f"{where}[]") for v in x]
        if isinstance(x, (set, frozenset)):
            return sorted(walk(v, where) for v in x)
        if isinstance(x, dict):
            return [(walk(k, where), walk(v, f"{where}[]")) for k, v in x.items()]
        if callable(x):
            raise AssertionError(
                f"{where}: a callable attribute; capture it or name it in NOT_STATE"
            )
        return obj(x, where)

    def obj(x: Any, where: str) -> Any:
        cls = type(x).__name__
        names: list[str] = []
        for klass in type(x).__mro__:
            names += [n for n in getattr(klass, "__slots__", ()) if n not in names]
        names += [n for n in getattr(x, "__dict__", {}) if n not in names]
        out = {}
        for name in names:
            if name == "__dict__" or f"{cls}.{name}" in snapshot.NOT_STATE:
                continue
            if not hasattr(x, name):
                continue
            out[name] = walk(getattr(x, name), f"{cls}.{name}")
        return (cls, out)

    return obj(unit, "Unit")


def test_not_state_names_attributes_that_exist() -> None:
    """Every attribute NOT_STATE names exists on a unit (a renamed one would leave it stale)."""
    unit = Driven.fresh().unit
    parts = {"Unit": unit, "AlarmManager": unit.alarms, "Counters": unit.counters,
             "Equipment": unit.equipment, "Interlocks": unit.interlocks,
             "StopReasons": unit.stops, "ModeStateTimes": unit.times,
             "Deadlines": unit.deadlines, "Publication": unit.publication,
             "Recipes": unit.recipes}  # fmt: skip
    unit.counters.snapshot("processed")
    unit.alarms.to_dict()
    for name in snapshot.NOT_STATE:
        cls, _, attr = name.partition(".")
        assert hasattr(parts[cls], attr), name


@pytest.mark.parametrize("seed", range(6))
def test_a_restored_unit_is_the_same_unit(seed: int) -> None:
    """Random campaigns; at random moments a snapshot through JSON gives a unit equal to the
    original in every attribute, which then publishes exactly what the original publishes."""
    rng = random.Random(seed)
    a = Driven.fresh()
    for _ in range(4):
        for step in random_inputs(rng, rng.randrange(20, 400), a.unit):
            a.apply(step)
        b = Driven.restored(snapshot.capture(a.unit))
        assert state_of(b.unit) == state_of(a.unit)
        a.out.clear()
        for step in random_inputs(rng, 300, a.unit):
            a.apply(step)
            b.apply(step)
        assert b.out == a.out
        assert len(a.out) > 50
        assert state_of(b.unit) == state_of(a.unit)


def test_a_snapshot_of_a_unit_with_a_store() -> None:
    """A unit with persistence (its periodic saves are deadlines too) restores the same way."""
    from packml_ros2.bag.replay import MemoryStore

    rng = random.Random(99)
    a = Driven.fresh(store=MemoryStore(None))
    for step in random_inputs(rng, 300, a.unit):
        a.apply(step)
    doc = json.loads(json.dumps(snapshot.capture(a.unit)))
    now = [float(doc["time"])]
    clock = FrozenClock(lambda: now[0])
    b = Driven(snapshot.restore(CONFIG, clock, doc, store=MemoryStore(None)), clock, now)
    a.out.clear()
    steps = random_inputs(rng, 300, a.unit)
    for step in steps:
        a.apply(step)
        b.apply(step)
    assert b.out == a.out and state_of(b.unit) == state_of(a.unit)


def test_a_million_inputs_then_a_snapshot() -> None:
    """A unit that has applied a million inputs (driven in-process, a production cycle of four
    EMs with counts, alarms and interlocks) is captured and restored; the next inputs give the
    same messages."""
    a = Driven.fresh()
    unit = a.unit
    ems = ("a", "b", "c")
    for em in ems:
        unit.em_seen(em, True)
    seen = 0
    t = T0
    begin = time.perf_counter()
    now = a.now
    em_complete, command, em_count, set_alarm = (unit.em_complete, unit.command, unit.em_count,
                                                 unit.set_alarm)  # fmt: skip
    cycle = executes = 0
    while seen < 1_000_000:
        cycle += 1
        t += 0.05
        now[0] = t
        state = unit.state
        if state is State.STOPPED or state is State.COMPLETE:
            command(Cmd.RESET)
        elif state is State.IDLE:
            command(Cmd.START)
        elif state is State.HELD:
            command(Cmd.UNHOLD)
        elif state is State.SUSPENDED:
            unit.em_interlock("a", False, False)  # cleared: the unit unsuspends itself
        elif state is State.ABORTED:
            set_alarm(101, 0, False)
            command(Cmd.CLEAR)
            seen += 1
        elif state is State.EXECUTE:
            executes += 1
            if executes % 7 == 0:
                command(Cmd.HOLD)
            elif executes % 101 == 0:
                set_alarm(101, 0, True)
            elif executes % 13 == 0:
                unit.em_interlock("a", True, False)
            elif executes % 11 == 0:
                set_alarm(103, 0, executes % 2 == 0)
        seen += 1
        seq, st = unit.sequence, int(unit.state)
        for em in ems:
            em_complete(em, st, seq)
            em_count(em, "processed", 0, 1)
        seen += 2 * len(ems)
        unit.drain()
    seconds = time.perf_counter() - begin
    print(f"{seen} inputs in {seconds:.1f} s, sequence {unit.sequence}")
    assert unit.alarms.history_dropped > 0  # the history ring went round
    assert unit.interlocks.attempt[1] > 1000  # interlocks suspended it, time and again
    b = Driven.restored(snapshot.capture(unit))
    assert state_of(b.unit) == state_of(unit)
    rng = random.Random(5)
    # (the unit was driven past its driver, which knows not what it showed: the stack light)
    a.driver = UnitDriver(unit, a.clock, a._emit)
    a.out.clear()
    for step in random_inputs(rng, 500, unit):
        a.apply(step)
        b.apply(step)
    assert b.out == a.out


# -- refusals ---------------------------------------------------------------------------------------------
def _doc() -> dict[str, Any]:
    a = Driven.fresh()
    for step in random_inputs(random.Random(3), 200, a.unit):
        a.apply(step)
    return json.loads(json.dumps(snapshot.capture(a.unit)))


@pytest.mark.parametrize(
    ("change", "reason"),
    [
        (lambda d: d.update(schema=2), "schema 2: this version reads schema 1 (the snapshot is newer"),
        (lambda d: d.update(schema="1"), "schema '1'"),
        (lambda d: d.update(unit="other"), "of unit 'other', not 'u'"),
        (lambda d: d["machine"].update(mode=7), "mode 7 is not configured"),
        (lambda d: d["machine"].update(state="x"), "cannot be restored: ValueError"),
        (lambda d: d["counters"]["values"]["processed"].pop(), "counters; the configuration has"),
        (lambda d: d["deadlines"]["heap"].append([0.0, 1, "boom", None]), "KeyError"),
        (lambda d: d["deadlines"]["heap"].append([-1.0, 1, "status", None]), "not a heap"),
        (lambda d: d["alarms"].update(history=[0] * 100), "history entries; the unit keeps 16"),
        (lambda d: d["times"].update(mode=99), "out of range"),
        (lambda d: d["times"]["state_current"].update({"9999": 1.0}), "outside"),
        (lambda d: d.pop("events"), "KeyError"),
    ],
)  # fmt: skip
def test_a_snapshot_that_does_not_fit_is_refused(change: Callable[[dict[str, Any]], None],
                                                  reason: str) -> None:  # fmt: skip
    doc = _doc()
    change(doc)
    with pytest.raises(snapshot.SnapshotError) as err:
        snapshot.restore(CONFIG, lambda: T0, doc)
    assert reason in str(err.value)
