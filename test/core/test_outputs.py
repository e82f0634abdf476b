"""The drained outputs (core/outputs.py): the engine queues a transition as plain tuples (time,
sequence, the other fields); whoever reads the outputs (iteration, index, slice) gets its typed
Transition record, also from a unit restored from a snapshot."""

from __future__ import annotations

from packml_ros2.core import Cmd, State, Transition, Trigger, Unit, snapshot, unit_config

from .helpers import FakeClock


def _unit() -> tuple[Unit, FakeClock]:
    clock = FakeClock()
    unit = Unit(unit_config("u"), clock=clock)
    unit.drain()
    return unit, clock


def _typed(outputs: object) -> None:
    for kind, value in outputs:  # type: ignore[attr-defined]
        if kind == "transition":
            assert type(value) is Transition, value


def test_a_drained_transition_is_a_typed_record() -> None:
    unit, clock = _unit()
    clock.advance(1.0)
    assert unit.command(Cmd.RESET, "operator:panel").accepted
    out = unit.drain()
    records = [value for kind, value in out if kind == "transition"]
    assert [(r.from_state, r.to_state, r.trigger, r.command, r.source) for r in records] == [
        (State.STOPPED, State.RESETTING, Trigger.COMMAND, Cmd.RESET, "operator:panel"),
        (State.RESETTING, State.IDLE, Trigger.STATE_COMPLETE, 0, "unit"),
    ]
    assert all(type(r) is Transition and r.time == clock.t for r in records)
    _typed(out)
    assert type(out[0][1]) is Transition  # by index
    assert all(type(v) is Transition for k, v in out[:2] if k == "transition")  # by slice
    assert list(out) == [(k, v) for k, v in out]
    raw = [value for kind, value in out.raw() if kind == "transition"]
    assert [(t, seq, *tail) for t, seq, tail in raw] == [tuple(r) for r in records]  # as queued


def test_a_restored_unit_drains_typed_records() -> None:
    unit, clock = _unit()
    again = snapshot.restore(unit.config, clock, snapshot.capture(unit))
    clock.advance(1.0)
    again.command(Cmd.RESET)
    out = again.drain()
    assert [kind for kind, _ in out].count("transition") == 2
    _typed(out)
    assert again.status_at(next(v for k, v in out if k == "transition")).state_current_name
