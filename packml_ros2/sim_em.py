"""A simulated equipment module, configured by the ``sim:`` block of an EM in the cell YAML.

Each acting state takes its configured duration; Execute cycles (``cycle_time``), counting a
product per cycle with defects at ``defect_rate``. Faults listed under ``faults`` are switched on
and off with a service per fault (``std_srvs/SetBool``):
``/<cell>/<unit>/<em>/fault/<name>`` — an alarm (by category it stops or aborts the unit), an
interlock (``blocked`` / ``starved``: the unit suspends), or ``repeat_complete``: a flaky link that
delivers every State Complete report of the EM a second time, :data:`REPEAT_AFTER` seconds later
(by then usually stale: the unit ignores and counts it), or ``refuse_recipe``: the next recipe
the unit sends is refused with the fault's message, once (the fault then switches itself off).
A changeover takes ``changeover_time`` seconds in every EM.

Run: ``em_node [--sim] <cell.yaml> <unit> <em> [<em> ...]`` (packml_ros2.em_launch.host_main: an
EM whose entry says ``run: module:Class`` is built from that class, one that says nothing or all
with ``--sim`` are simulated); ``packml launch`` starts these for every EM the file simulates or
runs as a Python class. Several EMs named: they run composed in one process on one executor (one
thread), as an integrator runs all EMs of one controller (``run.spin([em1, em2, ...])``).
"""

from __future__ import annotations

import asyncio
import contextlib
import random
import sys
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import partial
from typing import Any

from packml_interfaces.msg import Status
from std_srvs.srv import SetBool

from . import responses
from .core import schema as sc
from .core.config import CellConfig, load_cell
from .core.numbers import ACTING, State, parse_state
from .core.recipes import Recipe
from .core.schema import ConfigError, Node
from .equipment_module import EquipmentModule, RecipeRefused, StateContext, StatusView
from .ros import interface

SIM_KEYS = {"durations", "cycle_time", "counter", "counter_index", "defect_rate",
            "defect_counter_index", "consumed_per_cycle", "cycles_per_run", "lease", "faults",
            "seed", "fed_by", "buffer", "changeover_time"}  # fmt: skip
BUFFER_TICK = 0.1  # s between looks at the buffer of an EM fed by another unit, while it drains
FAULT_KEYS = {"kind", "alarm_id", "value", "category", "message"}
FAULT_KINDS = ("alarm", "warning", "blocked", "starved", "repeat_complete", "refuse_recipe")
#: ``repeat_complete``: seconds after which a State Complete report is sent again.
REPEAT_AFTER = 0.5


@dataclass(frozen=True)
class Fault:
    name: str
    kind: str  # alarm | warning | blocked | starved | repeat_complete
    alarm_id: int = 0
    value: int = 0
    category: int = -1
    message: str = ""


@dataclass(frozen=True)
class SimConfig:
    durations: Mapping[State, float] = field(default_factory=dict)
    cycle_time: float = 1.0
    counter: str = "processed"
    counter_index: int = 0
    defect_rate: float = 0.0
    defect_counter_index: int = 0
    consumed_per_cycle: int = 0
    cycles_per_run: int = 0  # Execute completes after this many cycles (0: runs until commanded)
    lease: float = 2.0  # heartbeats every lease/4; default: the unit's em_lease
    faults: Mapping[str, Fault] = field(default_factory=dict)
    seed: int | None = None
    #: the unit upstream that feeds this EM: while this unit runs and that one does not, the
    #: ``buffer`` (seconds of parts) empties; empty, the EM reports Starved until it runs again
    fed_by: str = ""
    buffer: float = 5.0
    changeover_time: float = 0.0  #: s an EM takes to apply a recipe (on_recipe)


def parse_sim(
    data: Mapping[str, Any], path: str = "sim", file: str = "<memory>", lease: float = 2.0
) -> SimConfig:
    """Validate a ``sim:`` block; ConfigError names the key path. ``lease``: the default of
    ``lease`` (give the unit's em_lease: the unit's lease decides, the EM beats a quarter of it)."""
    n = Node(dict(data), path)
    n.check_keys(SIM_KEYS)
    durations: dict[State, float] = {}
    for key, child in n.items_at("durations"):
        state = Node(key, child.path, child.problems).parse(sc.via(parse_state), State.UNDEFINED)
        if state not in ACTING:
            child.error(f"{key!r} is not an acting state")
            continue
        durations[state] = child.parse(sc.number(lo=0), 0.0)
    faults: dict[str, Fault] = {}
    for name, child in n.items_at("faults"):
        child.check_keys(FAULT_KEYS)
        kind = child.get("kind", sc.choice({k: k for k in FAULT_KINDS}), "alarm")
        if kind in ("alarm", "warning") and "alarm_id" not in child.mapping():
            child.error("an alarm fault needs alarm_id")
        faults[name] = Fault(
            name,
            kind,
            child.get("alarm_id", sc.integer(1), 0),
            child.get("value", sc.integer(), 0),
            child.get("category", sc.integer(-1, 9), -1),
            child.get("message", sc.text, ""),
        )
    cfg = SimConfig(
        durations=durations,
        cycle_time=n.get("cycle_time", sc.number(lo=0), 1.0),
        counter=n.get(
            "counter",
            sc.choice({k: k for k in ("processed", "consumed", "defective", "none")}),
            "processed",
        ),
        counter_index=n.get("counter_index", sc.integer(0), 0),
        defect_rate=n.get("defect_rate", sc.number(0.0, 1.0), 0.0),
        defect_counter_index=n.get("defect_counter_index", sc.integer(0), 0),
        consumed_per_cycle=n.get("consumed_per_cycle", sc.integer(0), 0),
        cycles_per_run=n.get("cycles_per_run", sc.integer(0), 0),
        lease=n.get("lease", sc.number(positive=True), lease),
        faults=faults,
        seed=n.get("seed", sc.integer(), None),
        fed_by=n.get("fed_by", sc.name, ""),
        buffer=n.get("buffer", sc.number(lo=0), 5.0),
        changeover_time=n.get("changeover_time", sc.number(lo=0), 0.0),
    )
    if n.problems:
        raise ConfigError(file, n.problems)
    return cfg


class SimulatedEm(EquipmentModule):
    """An EM whose work is simulated by time; see the module docstring."""

    def __init__(self, name: str, unit: str, cell: str, sim: SimConfig, **node_kwargs: Any) -> None:
        super().__init__(name, unit, cell, lease=sim.lease, **node_kwargs)
        self.sim = sim
        self.random = random.Random(
            sim.seed if sim.seed is not None else sum(map(ord, f"{unit}/{name}"))
        )
        self.faults_on: set[str] = set()
        self.buffer = sim.buffer  # seconds of parts left (fed_by)
        self.upstream_runs = False
        self._drain_timer = None
        if sim.fed_by:
            upstream = interface.TOPIC["status"]  # the status of the unit that feeds this one
            self.create_subscription(
                upstream.type,
                upstream.path(f"/{cell}/{sim.fed_by}"),
                self._on_upstream,
                upstream.qos,
            )
            self._drain_timer = self.create_timer(BUFFER_TICK, self._drain)
            self._drain_timer.cancel()  # runs only while the buffer drains (_watch_buffer)
        for fault in sim.faults.values():
            responses.create_service(
                self, SetBool, f"~/fault/{fault.name}", partial(self._srv_fault, fault)
            )

    @classmethod
    def from_cell(
        cls, cell: CellConfig, unit: str, em: str, *, file: str = "<memory>", **node_kwargs: Any
    ) -> SimulatedEm:
        """The simulated EM ``em`` of ``unit`` as its ``sim:`` block says (packml_ros2.em_launch)."""
        config = cell.units[unit]
        entry = next((e.sim for e in config.equipment_modules if e.name == em), {})
        sim = parse_sim(entry, f"units.{unit}.equipment_modules.{em}.sim", file, config.em_lease)
        return cls(em, unit, cell.cell, sim, **node_kwargs)

    # -- acting states: wait for the configured duration -------------------------------------------
    def hook_for(self, state: State):  # type: ignore[no-untyped-def]
        """Execute cycles; other acting states take their configured duration (none: at once)."""
        if state is State.EXECUTE:
            return self.execute
        return self._work if self.sim.durations.get(state) else None

    async def _work(self, ctx: StateContext) -> None:
        await asyncio.sleep(self.sim.durations[ctx.state])

    async def execute(self, ctx: StateContext) -> None:
        """Cycle: each cycle produces one product (possibly defective); Hold or Stop in the middle
        of a cycle lets the cycle finish first. ``cycle_time: 0``: no cycles, just stay."""
        if not self.sim.cycle_time:
            await asyncio.Event().wait()
        cycles = 0
        while not self.sim.cycles_per_run or cycles < self.sim.cycles_per_run:
            await ctx.finish(asyncio.sleep(self.sim.cycle_time))
            cycles += 1
            if self.sim.consumed_per_cycle:
                self.count("consumed", self.sim.consumed_per_cycle)
            if self.sim.counter != "none":
                self.count(self.sim.counter, 1, self.sim.counter_index)
            if self.sim.defect_rate and self.random.random() < self.sim.defect_rate:
                self.count("defective", 1, self.sim.defect_counter_index)

    # -- recipes -----------------------------------------------------------------------------------
    async def on_recipe(self, recipe: Recipe) -> None:
        """A changeover takes ``changeover_time``; a ``refuse_recipe`` fault refuses it, once."""
        await asyncio.sleep(self.sim.changeover_time)
        refusing = [f for f in self.faults_on if self.sim.faults[f].kind == "refuse_recipe"]
        if refusing:
            fault = self.sim.faults[refusing[0]]
            self.faults_on.discard(fault.name)
            raise RecipeRefused(fault.message or f"simulated refusal ({fault.name})")

    # -- fed by a unit upstream --------------------------------------------------------------------
    def _on_status(self, msg: StatusView) -> None:
        super()._on_status(msg)
        self._watch_buffer()

    def _on_upstream(self, msg: Status) -> None:
        self.upstream_runs = msg.state_current == State.EXECUTE
        if self.upstream_runs and self.buffer < self.sim.buffer:
            self.buffer = self.sim.buffer  # parts come again
            self._report_interlock()
        self._watch_buffer()

    def _draining(self) -> bool:
        """The buffer empties while this unit runs and the one upstream does not."""
        return not self.upstream_runs and self.state is State.EXECUTE and self.buffer > 0

    def _watch_buffer(self) -> None:
        """The buffer's timer runs only while it drains (an idle cell wakes nobody)."""
        timer = self._drain_timer
        if timer is None:
            return
        if not self._draining():
            timer.cancel()
        elif timer.is_canceled():
            timer.reset()

    def _drain(self) -> None:
        if not self._draining():
            self._watch_buffer()
            return
        self.buffer -= BUFFER_TICK
        if self.buffer <= 0:
            self.get_logger().warning(f"starved: {self.sim.fed_by} sends no parts")
            self._report_interlock()
            self._watch_buffer()

    def _report_interlock(self) -> None:
        kinds = {self.sim.faults[f].kind for f in self.faults_on}
        self.set_interlock(
            blocked="blocked" in kinds,
            starved="starved" in kinds or (bool(self.sim.fed_by) and self.buffer <= 0),
        )

    # -- fault injection ---------------------------------------------------------------------------
    def report_complete(self, state: int | None = None, sequence: int | None = None) -> None:
        state = int(self.state if state is None else state)
        sequence = self.sequence if sequence is None else sequence
        super().report_complete(state, sequence)
        if any(self.sim.faults[f].kind == "repeat_complete" for f in self.faults_on):
            again = threading.Timer(REPEAT_AFTER, self._repeat, (state, sequence))
            again.daemon = True
            again.start()

    def _repeat(self, state: int, sequence: int) -> None:
        if self.context.ok():
            with contextlib.suppress(Exception):  # (the node is going away)
                super().report_complete(state, sequence)

    def _srv_fault(
        self, fault: Fault, req: SetBool.Request, resp: SetBool.Response
    ) -> SetBool.Response:
        on = bool(req.data)
        if fault.kind in ("repeat_complete", "refuse_recipe"):
            (self.faults_on.add if on else self.faults_on.discard)(fault.name)
        elif fault.kind in ("blocked", "starved"):
            (self.faults_on.add if on else self.faults_on.discard)(fault.name)
            self._report_interlock()
        elif on:
            self.faults_on.add(fault.name)
            self.raise_alarm(
                fault.alarm_id,
                fault.value,
                fault.message,
                fault.category,
                warning=fault.kind == "warning",
            )
        else:
            self.faults_on.discard(fault.name)
            self.clear_alarm(fault.alarm_id, fault.value)
        resp.success = True
        resp.message = f"{fault.name} {'on' if on else 'off'} ({fault.kind})"
        self.get_logger().warning(f"fault {resp.message}")
        return resp


def create(cell_file: str, unit: str, em: str, **node_kwargs: Any) -> SimulatedEm:
    cell = load_cell(cell_file)
    if unit not in cell.units:
        raise SystemExit(f"{cell_file} has no unit {unit!r} (units: {', '.join(cell.units)})")
    return SimulatedEm.from_cell(cell, unit, em, file=cell_file, **node_kwargs)


def main(argv: Sequence[str] | None = None) -> int:
    """``em_node``: the EM host (packml_ros2.em_launch.host_main)."""
    from .em_launch import host_main

    return host_main(argv)


if __name__ == "__main__":
    sys.exit(main())
