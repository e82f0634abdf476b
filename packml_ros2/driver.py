"""Driving a :class:`~packml_ros2.core.Unit` and turning its outputs into messages — the one place
that does it, used by the unit node (live) and by ``packml replay`` (offline), so both produce the
same messages in the same order:

1. before an input at time t, every deadline due by t is fired and published one at a time;
2. the input is applied with the engine's clock frozen at t (the time the input log records);
3. its outputs are published.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any, TypeVar

from . import convert
from .core import Unit, inputlog, packtags, snapshot
from .core.counters import KINDS
from .core.liveliness import Liveliness
from .core.outputs import RawTransition
from .core.packtags import AdminView
from .core.unit import StatusMark, Transition

T = TypeVar("T")
#: Schema of the JSON object a ``UnitSnapshot`` carries around core.snapshot's engine state:
#: ``schema``, ``engine``, ``persistence`` (the unit has a store), ``input_schema`` (of its
#: input log) and ``published`` (messages per output topic so far).
SNAPSHOT_SCHEMA = 1
#: emit(topic, message): topic is "status", "transitions", "admin", "alarms" or "log".
Emit = Callable[[str, Any], None]


class FrozenClock:
    """The engine's clock: the node's (or bag's) time, frozen while an input is applied."""

    def __init__(self, source: Callable[[], float]) -> None:
        self.source = source
        self.frozen: float | None = None

    def __call__(self) -> float:
        return self.frozen if self.frozen is not None else self.source()


class UnitDriver:
    def __init__(self, unit: Unit, clock: FrozenClock, emit: Emit) -> None:
        self.unit = unit
        self.clock = clock
        self.emit = emit
        self.name = unit.config.name
        #: Alarm and Count messages made once per state: every Admin carries all of them.
        self.cache = convert.MessageCache()
        self.modes = convert.mode_slots(unit.config)
        #: the stack light as last published: the unit's now (a node publishes it at its start,
        #: :meth:`stack_light_message`; a driver of a restored unit goes on from it)
        self._light = self._light_key(self.stack_light_message())

    def catch_up(self, now: float) -> None:
        """Fire the deadlines due by ``now``, publishing after each."""
        while self.unit.fire_next(now):
            self.flush()

    def call(self, now: float, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        """Apply an input (a Unit method) at time ``now`` and publish what it caused."""
        self.catch_up(now)
        self.clock.frozen = now
        try:
            return fn(*args, **kwargs)
        finally:
            self.flush()
            self.clock.frozen = None

    def clock_step(self, now: float, offset: float) -> Any:
        """The wall clock stepped by ``offset`` and reads ``now``: what was due by the same
        instant on the old timeline (``now - offset``) fires first, then the engine's timeline
        moves (:meth:`~packml_ros2.core.Unit.clock_step`, at ``now``)."""
        self.catch_up(now - offset)
        self.clock.frozen = now
        try:
            return self.unit.clock_step(offset)
        finally:
            self.flush()
            self.clock.frozen = None

    def report(
        self, now: float, msg: Any, liveliness: Liveliness, tick: float | None = None
    ) -> None:
        """An ``EmReport`` received at ``now``, applied as the engine inputs it stands for: every
        report is a heartbeat (``em_seen`` when the EM was not alive), then its kind's input. The
        unit node and the synthetic recorder (bag/synthetic.py) both come here. ``tick``: the
        time on the leases' clock (the node's steady clock; default ``now``)."""
        unit, run, name, kind, cls = self.unit, self.call, msg.em, msg.kind, type(msg)
        if kind == cls.KIND_LEAVE:
            if liveliness.left(name):
                run(now, unit.em_lost, name, "left")
            return
        if (
            liveliness.seen(name, now if tick is None else tick)
            and not run(now, unit.em_seen, name, True).accepted
        ):
            liveliness.forget(name)  # not registered: its next report asks again
            return  # the rest of a report of an EM the unit does not know changes nothing
        warning = liveliness.announce(name, msg.lease)
        if warning is not None:
            self.emit("log", ("warn", warning))
        if kind == cls.KIND_STATE_COMPLETE:
            run(now, unit.em_complete, name, msg.state, msg.sequence)
        elif kind == cls.KIND_COMMAND_REQUEST:
            run(now, unit.em_request, name, msg.command)
        elif kind == cls.KIND_INTERLOCK:
            run(now, unit.em_interlock, name, msg.blocked, msg.starved, msg.material_interlock)
        elif kind == cls.KIND_COUNT:
            if msg.counter < len(KINDS):
                run(now, unit.em_count, name, KINDS[msg.counter], msg.counter_index, msg.increment)
        elif kind == cls.KIND_ALARM:
            run(
                now,
                unit.em_alarm,
                name,
                msg.alarm_id,
                msg.alarm_value,
                msg.alarm_active,
                msg.warning,
                msg.category,
                msg.message,
            )
        elif kind == cls.KIND_RECIPE:
            run(now, unit.em_recipe, name, msg.sequence, msg.recipe_accepted, msg.message)

    def replay(self, now: float, name: str, args: dict[str, Any]) -> Any:
        """Apply a logged input again (name and arguments as ``Unit.on_input`` reported them)."""
        if name == inputlog.CLOCK_STEP.name:
            return self.clock_step(now, float(args["offset"]))
        return self.call(now, self.unit.apply_input, name, args)

    def flush(self) -> None:
        unit = self.unit
        for kind, item in unit.drain().raw():  # (a transition as (time, sequence, other fields))
            if kind == "transition":
                self.emit("transitions", convert.transition(self.name, item))
                self.emit("status", self.status_message(item))
            elif kind == "status":
                self.emit("status", self.status_message(item))
            elif kind == "alarms":
                self.emit(
                    "alarms", convert.alarm_list(self.name, unit.now, unit.alarms, self.cache)
                )
            elif kind == "admin":
                self.emit("admin", self.admin_message(item))
            elif kind == "recipe":
                self.emit("recipe", convert.recipe_order(unit.now, item))
            else:
                self.emit("log", item)

    def snapshot_message(self, index: int, published: dict[str, int], persistence: bool) -> Any:
        """``UnitSnapshot``: the engine state now, after input ``index`` (between inputs), with
        what a replay from it needs besides."""
        from packml_interfaces.msg import UnitSnapshot

        state = {
            "schema": SNAPSHOT_SCHEMA,
            "engine": snapshot.capture(self.unit),
            "persistence": persistence,
            "input_schema": inputlog.SCHEMA,
            "published": dict(published),
        }
        return UnitSnapshot(
            stamp=convert.stamp(self.unit.now),
            index=index,
            unit=self.name,
            state_json=json.dumps(state, separators=(",", ":")),
        )

    def admin_message(self, view: AdminView | None = None) -> Any:
        """The Admin message of ``view`` (default: the unit's admin data now)."""
        return convert.admin(self.unit.admin() if view is None else view, self.cache, self.modes)

    def stack_light_message(self) -> Any:
        """The unit's stack light now (``StackLight``)."""
        return convert.stack_light(packtags.stack_light(self.unit, self.unit.state))

    @staticmethod
    def _light_key(light: Any) -> tuple[Any, ...]:
        return (tuple(light.colors), bytes(light.modes), light.horn)

    def status_message(self, mark: Transition | RawTransition | StatusMark) -> Any:
        msg = convert.status(self.unit.status_at(mark))
        light = msg.stack_light
        key = self._light_key(light)
        if key != self._light:  # the stack light's own topic, on change
            self._light = key
            self.emit("stack_light", light)
        return msg
