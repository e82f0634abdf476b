"""The PackML engine: pure Python, no rclpy; the clock is a parameter.

>>> from packml_ros2.core import Unit, unit_config, Cmd
>>> t = [0.0]
>>> unit = Unit(unit_config("filler"), clock=lambda: t[0])
>>> unit.command(Cmd.RESET).message
'RESET accepted: STOPPED -> RESETTING'
>>> unit.state.name  # no EMs: acting states complete at once
'IDLE'
"""

from . import inputlog, rules
from .alarms import AlarmDef, AlarmEvent, AlarmManager
from .config import (
    CellConfig,
    ConfigError,
    EmConfig,
    UnitConfig,
    load_cell,
    parse_cell,
    unit_config,
)
from .numbers import (
    ACTING,
    WAIT,
    Cmd,
    Mode,
    State,
    command_name,
    parse_command,
    parse_state,
    state_name,
)
from .packtags import AdminView, StatusView, flat_tags
from .persistence import Store, StoreError
from .reasons import Answer, Reason
from .unit import CommandRequest, CompleteReport, ModeRequest, Transition, Trigger, Unit

__all__ = [
    "ACTING",
    "WAIT",
    "AdminView",
    "AlarmDef",
    "AlarmEvent",
    "AlarmManager",
    "Answer",
    "CellConfig",
    "Cmd",
    "CommandRequest",
    "CompleteReport",
    "ConfigError",
    "EmConfig",
    "Mode",
    "ModeRequest",
    "Reason",
    "State",
    "StatusView",
    "Store",
    "StoreError",
    "Transition",
    "Trigger",
    "Unit",
    "UnitConfig",
    "command_name",
    "flat_tags",
    "inputlog",
    "load_cell",
    "parse_cell",
    "parse_command",
    "parse_state",
    "rules",
    "state_name",
    "unit_config",
]
