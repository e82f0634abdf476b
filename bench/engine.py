"""Engine benchmark: transitions per second of packml_ros2's engine, of packmlpy and of a bare
dict-table state machine (the floor) on the same full cycle, measured side by side in one run; the
two state-machine libraries Python users pick (``transitions``, ``python-statemachine``) on a bare
6-state cycle of the same states in the same run; the cost per transition with 8 EMs reporting and
alarms defined, and with persistence (the write-ahead journal). Prints JSON.

    python bench/engine.py [--seconds 0.4] [--repeats 9]

The full cycle is the one packmlpy can run: Idle -> Starting -> Execute -> Completing -> Complete
-> Resetting -> Idle (6 transitions). packmlpy completes acting states on its own; our unit has no
EMs, so it completes acting states at once too, and Execute is left with the Complete command.
The floor is what no engine of this cycle can beat in Python (:class:`FloorMachine`): a method
per command, one dict look-up of (state, command) in the same TR88 table, State Complete followed
by dict look-ups, and what makes the same transitions observable: a sequence number and a record
per transition in an output queue, drained; no modes, guards, times, EMs or alarms. It is driven
by the same loop as ours (:func:`cycle_loop`: the clock moved, the outputs drained every cycle).
Ours queues a transition as plain tuples of its 11 fields (core/outputs.py: typed as its
``Transition`` when iterated; the unit node reads the fields by position); the loop does not read
the outputs (nor the floor's 5-field records); ``with_outputs_read`` is ours with every drained
output read as the unit node reads it, beside it.
``floor_lookups_only`` is the floor of earlier runs (the look-ups and a counter, no clock, no
record, no drain), kept for comparison. Everything runs in this process, interleaved, repeats
alternating, so machine noise hits all alike; a ratio is the median of the repeats' ratios (each
repeat times the engines back to back).
"""

from __future__ import annotations

import argparse
import asyncio
import functools
import gc
import json
import operator
import platform
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Protocol

from packml_ros2.core import Cmd, State, Store, Unit, unit_config
from packml_ros2.core.alarms import AlarmDef
from packml_ros2.core.config import EmConfig
from packml_ros2.core.rules import STATE_COMPLETE, build_table

CYCLE_TRANSITIONS = 6


def settable_clock() -> tuple[list[float], Callable[[], float]]:
    """The engine takes its clock as a parameter: here ``now[0]`` is the time and ``clock()``
    reads it. (A C-level callable, so reading the clock runs no Python code of the bench.)"""
    now = [1_700_000_000.0]
    return now, functools.partial(operator.getitem, now, 0)


class Machine(Protocol):
    state: State
    sequence: int

    def command(self, cmd: Cmd) -> object: ...
    def drain(self) -> object: ...


def cycle_loop(machine: Machine, now: list[float], read: bool = False) -> Callable[[int], int]:
    """The full cycle ``cycles`` times on ``machine`` (ours or the floor: the same loop), the
    clock 1 ms further each cycle, the outputs drained (and with ``read``, read: every output
    taken as a publisher takes it); returns the transitions made."""

    def run(cycles: int) -> int:
        before = machine.sequence
        command, drain = machine.command, machine.drain
        start, complete, reset = Cmd.START, Cmd.COMPLETE, Cmd.RESET
        for _ in range(cycles):
            now[0] += 0.001
            command(start)  # Idle -> Starting -> Execute
            command(complete)  # Execute -> Completing -> Complete
            command(reset)  # Complete -> Resetting -> Idle
            if read:  # as the unit node's publisher reads them (packml_ros2.driver)
                for kind, item in drain().raw():  # type: ignore[attr-defined]
                    if kind == "transition":  # (convert.transition unpacks the 11 fields)
                        _t, _s, (_f, _to, _fm, _tm, _tr, _c, _src, _sk, _d) = item
            else:
                drain()
        assert machine.state is State.IDLE
        return machine.sequence - before

    return run


def ours_cycle_runner(store_folder: str | None = None, read: bool = False) -> Callable[[int], int]:
    """Our unit without EMs; with ``store_folder``, with persistence there (every command
    journals its changes before it answers); with ``read``, its outputs read as well, as the
    unit node's publisher reads them (by position, as queued)."""
    now, clock = settable_clock()
    store = Store(Path(store_folder) / "bench.sqlite3", "bench") if store_folder else None
    unit = Unit(unit_config("bench"), clock=clock, store=store)
    unit.command(Cmd.RESET)  # Stopped -> Resetting -> Idle
    assert unit.state is State.IDLE

    return cycle_loop(unit, now, read)


class FloorMachine:
    """The bare dict-table state machine (the floor): a method per command, one dict look-up of
    (state, command) in the same TR88 table, State Complete followed by dict look-ups, and for
    each transition what makes it observable at all: a sequence number and a record (time,
    sequence, from, to, command) in an output queue taken by ``drain``, as ours does. No modes,
    guards, times, EMs, alarms or persistence."""

    __slots__ = ("_clock", "_out", "sequence", "state")

    def __init__(self, clock: Callable[[], float]) -> None:
        self._clock = clock
        self._out: list[tuple[float, int, State, State, int]] = []
        self.state = State.IDLE
        self.sequence = 0

    def command(self, cmd: Cmd) -> bool:
        to = FLOOR_TABLE.get((self.state, cmd))
        if to is None:
            return False
        t, seq, frm, out = self._clock(), self.sequence, self.state, self._out.append
        while True:
            seq += 1
            out((t, seq, frm, to, cmd))
            after = FLOOR_STATE_COMPLETE.get(to)
            if after is None:
                break
            frm, to, cmd = to, after, Cmd.UNDEFINED
        self.state, self.sequence = to, seq
        return True

    def drain(self) -> list[tuple[float, int, State, State, int]]:
        out, self._out = self._out, []
        return out


FLOOR_TABLE: dict[tuple[State, Cmd], State] = dict(build_table().commands)
#: State Complete of the states that complete at once (without EMs); Execute waits for Complete.
FLOOR_STATE_COMPLETE: dict[State, State] = {
    s: to for s, to in STATE_COMPLETE.items() if s is not State.EXECUTE
}


def floor_cycle_runner() -> Callable[[int], int]:
    """The floor (:class:`FloorMachine`), driven by the same loop as ours (clock, drain)."""
    now, clock = settable_clock()
    machine = FloorMachine(clock)

    return cycle_loop(machine, now)


def lookup_floor_cycle_runner() -> Callable[[int], int]:
    """The floor of earlier runs, kept for comparison: the look-ups alone, no clock, no
    sequence, no record of a transition (nothing an observer could see)."""
    table = FLOOR_TABLE
    state_complete = FLOOR_STATE_COMPLETE
    machine = {"state": State.IDLE, "transitions": 0}

    def command(cmd: Cmd) -> bool:
        to = table.get((machine["state"], cmd))
        if to is None:
            return False
        n = 1
        while to in state_complete:
            to = state_complete[to]
            n += 1
        machine["state"] = to
        machine["transitions"] += n
        return True

    def run(cycles: int) -> int:
        before = machine["transitions"]
        start, complete, reset = Cmd.START, Cmd.COMPLETE, Cmd.RESET
        for _ in range(cycles):
            command(start)
            command(complete)
            command(reset)
        assert machine["state"] is State.IDLE
        return machine["transitions"] - before

    return run


def packmlpy_cycle_runner() -> Callable[[int], int] | None:
    try:
        from packmlpy.statemachine.StateMachineBuilder import StateMachineBuilder
    except ImportError:
        return None
    loop = asyncio.new_event_loop()
    sm = StateMachineBuilder().build()  # starts in Idle

    async def cycles_async(cycles: int) -> None:
        for _ in range(cycles):
            await sm.start()  # Idle -> Starting -> Execute -> Completing -> Complete
            await sm.reset()  # Complete -> Resetting -> Idle

    def run(cycles: int) -> int:
        loop.run_until_complete(cycles_async(cycles))
        assert sm.state.name == "Idle", sm.state
        return cycles * CYCLE_TRANSITIONS

    return run


#: The bare 6-state cycle the general-purpose libraries run: the same states and order as
#: the full cycle, each transition a trigger of its own (State Complete is the ``done`` trigger:
#: these libraries have no acting states), no guards, callbacks, modes or outputs.
BARE_CYCLE = ("Idle", "Starting", "Execute", "Completing", "Complete", "Resetting")
BARE_TRIGGERS = ("start", "done", "complete", "done", "reset", "done")


def transitions_cycle_runner() -> Callable[[int], int] | None:
    """``transitions`` (pytransitions): a Machine on a plain model, one trigger per transition."""
    try:
        from transitions import Machine as Transitions
    except ImportError:
        return None

    class Model:
        state: str

    model = Model()
    edges = [
        {"trigger": trigger, "source": frm, "dest": BARE_CYCLE[(i + 1) % len(BARE_CYCLE)]}
        for i, (frm, trigger) in enumerate(zip(BARE_CYCLE, BARE_TRIGGERS, strict=True))
    ]
    Transitions(model=model, states=list(BARE_CYCLE), transitions=edges, initial="Idle")
    start, done, complete, reset = (
        getattr(model, t) for t in ("start", "done", "complete", "reset")
    )

    def run(cycles: int) -> int:
        for _ in range(cycles):
            start()
            done()
            complete()
            done()
            reset()
            done()
        assert model.state == "Idle", model.state
        return cycles * CYCLE_TRANSITIONS

    return run


def statemachine_cycle_runner() -> Callable[[int], int] | None:
    """``python-statemachine``: a StateMachine class of the 6 states, one event per transition."""
    try:
        from statemachine import State as S
        from statemachine import StateMachine
    except ImportError:
        return None

    class Cycle(StateMachine):  # type: ignore[misc]
        idle = S(initial=True)
        starting = S()
        execute = S()
        completing = S()
        complete = S()
        resetting = S()
        start = idle.to(starting)
        done = starting.to(execute) | completing.to(complete) | resetting.to(idle)
        finish = execute.to(completing)
        reset = complete.to(resetting)

    sm = Cycle()

    def run(cycles: int) -> int:
        send = sm.send
        for _ in range(cycles):
            send("start")
            send("done")
            send("finish")
            send("done")
            send("reset")
            send("done")
        assert sm.idle.is_active
        return cycles * CYCLE_TRANSITIONS

    return run


def ours_with_ems_runner(ems: int = 8, alarms: int = 32) -> Callable[[int], int]:
    """Resetting, Starting, Completing each wait for State Complete from every EM."""
    now, clock = settable_clock()
    config = unit_config(
        "bench_ems",
        equipment_modules=tuple(EmConfig(f"em{i}") for i in range(ems)),
        alarms=tuple(AlarmDef(100 + i, 0, f"alarm {i}", i % 10) for i in range(alarms)),
    )
    unit = Unit(config, clock=clock)
    names = [f"em{i}" for i in range(ems)]
    for name in names:
        unit.em_seen(name)

    def complete_all() -> None:
        state, seq = unit.state, unit.sequence
        for name in names:
            unit.em_complete(name, state, seq)

    unit.command(Cmd.RESET)
    complete_all()
    assert unit.state is State.IDLE

    def run(cycles: int) -> int:
        before = unit.sequence
        command, drain = unit.command, unit.drain
        start, complete, reset = Cmd.START, Cmd.COMPLETE, Cmd.RESET
        for _ in range(cycles):
            now[0] += 0.001
            command(start)
            complete_all()  # Starting -> Execute
            command(complete)
            complete_all()  # Completing -> Complete
            command(reset)
            complete_all()  # Resetting -> Idle
            drain()
        assert unit.state is State.IDLE
        return unit.sequence - before

    return run


def calibrate(run: Callable[[int], int], seconds: float) -> int:
    cycles = 10
    while True:
        t0 = time.perf_counter()
        run(cycles)
        dt = time.perf_counter() - t0
        if dt >= seconds / 4:
            return max(10, int(cycles * seconds / dt))
        cycles *= 4


def measure(
    runners: dict[str, Callable[[int], int]], seconds: float, repeats: int
) -> dict[str, list[float]]:
    """Seconds per transition of each runner, ``repeats`` times, interleaved."""
    sizes = {name: calibrate(run, seconds) for name, run in runners.items()}
    samples: dict[str, list[float]] = {name: [] for name in runners}
    gc.disable()
    try:
        for _ in range(repeats):
            for name, run in runners.items():
                t0 = time.perf_counter()
                transitions = run(sizes[name])
                samples[name].append((time.perf_counter() - t0) / transitions)
    finally:
        gc.enable()
    return samples


def summary(per_transition: list[float]) -> dict[str, float]:
    median = statistics.median(per_transition)
    best = min(per_transition)
    return {
        "us_per_transition_median": round(median * 1e6, 3),
        "us_per_transition_best": round(best * 1e6, 3),
        "transitions_per_second_median": round(1 / median),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=0.4, help="target time per sample")
    parser.add_argument("--repeats", type=int, default=9)
    args = parser.parse_args()

    runners: dict[str, Callable[[int], int]] = {
        "packml_ros2": ours_cycle_runner(),
        "floor": floor_cycle_runner(),
        "floor_lookups_only": lookup_floor_cycle_runner(),
    }
    theirs = packmlpy_cycle_runner()
    if theirs is not None:
        runners["packmlpy"] = theirs
    peers = {"transitions": transitions_cycle_runner(), "python-statemachine": statemachine_cycle_runner()}  # fmt: skip
    runners.update((name, run) for name, run in peers.items() if run is not None)
    runners["packml_ros2_8_ems_32_alarms"] = ours_with_ems_runner()
    runners["packml_ros2_outputs_read"] = ours_cycle_runner(read=True)
    with tempfile.TemporaryDirectory(prefix="packml_bench_") as folder:
        runners["packml_ros2_with_persistence"] = ours_cycle_runner(folder)
        samples = measure(runners, args.seconds, args.repeats)

    result: dict[str, object] = {
        "benchmark": "engine",
        "python": platform.python_version(),
        "cycle": "Idle>Starting>Execute>Completing>Complete>Resetting>Idle (6 transitions)",
        "repeats": args.repeats,
        "engines": {name: summary(values) for name, values in samples.items()},
    }

    def ratio(slow: str, fast: str) -> tuple[float, list[float]]:
        # Each repeat measures the engines back to back: the ratio of a repeat compares them
        # under the same machine conditions; the median of those ratios is the result.
        ratios = [s / f for f, s in zip(samples[fast], samples[slow], strict=True)]
        return round(statistics.median(ratios), 2), [round(r, 2) for r in ratios]

    result["ratio_packml_ros2_over_floor"], by_repeat = ratio("packml_ros2", "floor")
    result["ratio_over_floor_by_repeat"] = by_repeat
    result["target_ratio_over_floor"] = 1.5
    result["ratio_packml_ros2_over_floor_lookups_only"], _ = ratio(
        "packml_ros2", "floor_lookups_only"
    )
    if "packmlpy" in samples:
        speedup, by_repeat = ratio("packmlpy", "packml_ros2")
        result["ratio_packml_ros2_over_packmlpy"] = round(speedup, 1)
        result["ratio_by_repeat"] = [round(r, 1) for r in by_repeat]
        result["target_ratio"] = 50
    else:
        result["packmlpy"] = "not installed (pip install packmlpy) - no ratio"
    result["peers_on_a_bare_6_state_cycle"] = {
        name: (
            {
                "us_per_transition_median": summary(samples[name])["us_per_transition_median"],
                "ratio_over_packml_ros2": ratio(name, "packml_ros2")[0],
            }
            if name in samples
            else f"not installed (pip install {name}) - not measured"
        )
        for name in peers
    }
    ems = summary(samples["packml_ros2_8_ems_32_alarms"])
    result["with_8_ems"] = {
        "us_per_transition_median": ems["us_per_transition_median"],
        "target_us": 3,
        "note": "per transition, including the 8 State Complete reports of each acting state",
    }
    read, _ = ratio("packml_ros2_outputs_read", "floor")
    result["with_outputs_read"] = {
        "us_per_transition_median": summary(samples["packml_ros2_outputs_read"])[
            "us_per_transition_median"
        ],
        "ratio_over_floor": read,
        "note": "the drained outputs read as the unit node reads them (records by position)",
    }
    stored = summary(samples["packml_ros2_with_persistence"])
    cost, _ = ratio("packml_ros2_with_persistence", "packml_ros2")
    result["with_persistence"] = {
        "us_per_transition_median": stored["us_per_transition_median"],
        "ratio_over_without": cost,
        "note": "every command journals its changes (one write()) before it answers",
    }
    json.dump(result, sys.stdout, indent=2)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
