"""convert.build(): messages made without rosidl's eager defaults must equal the checked ones, and
every field must be set (a field added to a .msg and forgotten in convert.py fails here, although
the tests' ROS_PYTHON_CHECK_FIELDS=1 makes convert use the checking constructors)."""

from __future__ import annotations

import pytest
from rclpy.serialization import deserialize_message, serialize_message

from packml_ros2 import convert
from packml_ros2.core import Cmd, Unit, unit_config
from packml_ros2.core.alarms import AlarmDef
from packml_ros2.core.config import EmConfig


def _views():
    t = [1_700_000_000.0]
    unit = Unit(
        unit_config(
            "filler",
            equipment_modules=(EmConfig("robot"),),
            alarms=(AlarmDef(65, 0, "Stop PB", 2),),
        ),
        clock=lambda: t[0],
    )
    unit.em_seen("robot")
    unit.set_alarm(65)
    t[0] += 3.5
    unit.set_alarm(65, active=False)
    unit.ack_alarms()
    unit.command(Cmd.RESET)
    return unit


@pytest.mark.parametrize("kind", ["status", "admin", "alarm", "alarm_list"])
def test_fast_construction_equals_the_checked_one(
    monkeypatch: pytest.MonkeyPatch, kind: str
) -> None:
    unit = _views()
    make = {
        "status": lambda: convert.status(unit.status()),
        "admin": lambda: convert.admin(unit.admin(), convert.MessageCache()),
        "alarm": lambda: convert.alarm(next(iter(unit.alarms.history))),
        "alarm_list": lambda: convert.alarm_list("filler", unit.now, unit.alarms),
    }[kind]
    monkeypatch.setattr(convert, "_CHECKED", True)
    checked = make()
    monkeypatch.setattr(convert, "_CHECKED", False)
    fast = make()
    assert type(fast) is type(checked)
    for name in type(checked).get_fields_and_field_types():
        assert hasattr(fast, name), f"{type(fast).__name__}.{name} is not set by convert"
    data = serialize_message(fast)
    assert deserialize_message(data, type(fast)) == checked


def test_admin_and_alarms_carry_the_configured_entries_not_padding() -> None:
    """What `ros2 topic echo .../admin` and `.../alarms` print: the time arrays reach the highest
    configured mode (index = mode, 18 states per mode), the first-out per category the highest
    category with a first-out (none: empty); before, 32 and 32 x 18 entries and 10 blank alarms
    made each message hundreds of lines long."""
    from packml_ros2.driver import FrozenClock, UnitDriver

    unit = _views()
    sent: list[tuple[str, object]] = []
    driver = UnitDriver(unit, FrozenClock(lambda: unit.now), lambda t, m: sent.append((t, m)))
    admin = driver.admin_message()
    modes = max(unit.config.modes) + 1
    assert modes == 4  # the three default modes: production 1, maintenance 2, manual 3
    assert len(admin.mode_current_time) == len(admin.mode_cumulative_time) == modes
    assert len(admin.state_current_time) == len(admin.state_cumulative_time) == modes * 18
    assert admin.mode_cumulative_time[unit.mode] > 0  # the times themselves are all there
    empty = convert.alarm_list("filler", unit.now, Unit(unit.config, clock=lambda: unit.now).alarms)
    assert list(empty.first_out_by_category) == []
    with_first_out = convert.alarm_list("filler", unit.now, unit.alarms)  # category 2 raised
    assert [a.id for a in with_first_out.first_out_by_category] == [0, 0, 65]


def test_admin_goes_out_on_change_and_as_a_slow_heartbeat() -> None:
    """Admin is published when something in it changes (a transition, a count, an alarm) and
    otherwise every admin_period, 5 s by default (it was every second: a flood in a terminal)."""
    t = [1_700_000_000.0]
    unit = Unit(unit_config("filler"), clock=lambda: t[0])
    for _ in range(3):  # the start-up's changes go out (coalesced)
        t[0] += 1.0
        unit.advance()
    unit.drain()
    for _ in range(20):  # 20 s with nothing happening
        t[0] += 1.0
        unit.advance()
    assert [kind for kind, _ in unit.drain()].count("admin") == 4  # at 5, 10, 15 and 20 s
    unit.command(Cmd.RESET)  # at 23 s: its admin goes out within a second, before the heartbeat
    for _ in range(4):
        t[0] += 0.25
        unit.advance()
    assert [kind for kind, _ in unit.drain()].count("admin") == 1


def test_a_transition_as_queued_converts_as_its_typed_record() -> None:
    """The unit node reads the drained outputs as queued (Outputs.raw: a transition as plain
    tuples, time, sequence and the other fields); its TransitionEvent and status equal those of
    the typed record."""
    unit = _views()
    unit.drain()
    unit.command(Cmd.STOP)
    out = unit.drain()
    raw = [item for kind, item in out.raw() if kind == "transition"]
    typed = [item for kind, item in out if kind == "transition"]
    assert raw and [type(r) for r in raw] == [tuple] * len(raw)
    for r, t in zip(raw, typed, strict=True):
        assert serialize_message(convert.transition("filler", r)) == serialize_message(
            convert.transition("filler", t)
        )
        assert unit.status_at(r) == unit.status_at(t)


def test_every_field_of_the_status_view_reaches_the_status_message() -> None:
    """``convert.status`` is generated from the message's fields (issue 28): a field of the view
    changed alone changes the message, so none is dropped on the way (the unit's and a PLC
    bridge's status alike go through it)."""
    import dataclasses

    from packml_ros2.core.config import Descriptor, Product
    from packml_ros2.core.packtags import RemoteInterfaceView, StackLightView, StatusView

    view = _views().status()
    base = convert.status(view)
    empty = {"parameter": (Descriptor(1, "speed", "ppm", 2.0),),
             "product": (Product(7, (), ()),),
             "remote_interface": (RemoteInterfaceView(1, 2, 3),)}  # fmt: skip
    for f in dataclasses.fields(StatusView):
        value = getattr(view, f.name)
        if isinstance(value, StackLightView):
            other: object = value._replace(horn=not value.horn)
        elif isinstance(value, bool):
            other = not value
        elif isinstance(value, int | float):
            other = value + 1
        elif isinstance(value, str):
            other = value + "x"
        else:
            other = value[:-1] if value else empty[f.name]
        assert convert.status(dataclasses.replace(view, **{f.name: other})) != base, f.name
