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
