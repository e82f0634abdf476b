"""The PackML engine: pure Python, no rclpy; the clock is a parameter.

>>> from packml_ros2.core import Unit, unit_config, Cmd
>>> t = [0.0]
>>> unit = Unit(unit_config("filler"), clock=lambda: t[0])
>>> unit.command(Cmd.RESET).message
'RESET accepted: STOPPED -> RESETTING'
>>> unit.state.name  # no EMs: acting states complete at once
'IDLE'
"""

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # the names, for type checkers; at run time each is imported when first used
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
    from .requests import CommandRequest, CompleteReport, ModeRequest
    from .unit import Transition, Trigger, Unit

#: name -> the module that defines it (a tool that needs only ``numbers`` does not pay for the
#: configuration parser, the engine and the store: ``packml status`` starts faster)
_LAZY = {
    "inputlog": ".inputlog",
    "rules": ".rules",
    "AlarmDef": ".alarms",
    "AlarmEvent": ".alarms",
    "AlarmManager": ".alarms",
    "CellConfig": ".config",
    "ConfigError": ".config",
    "EmConfig": ".config",
    "UnitConfig": ".config",
    "load_cell": ".config",
    "parse_cell": ".config",
    "unit_config": ".config",
    "ACTING": ".numbers",
    "WAIT": ".numbers",
    "Cmd": ".numbers",
    "Mode": ".numbers",
    "State": ".numbers",
    "command_name": ".numbers",
    "parse_command": ".numbers",
    "parse_state": ".numbers",
    "state_name": ".numbers",
    "AdminView": ".packtags",
    "StatusView": ".packtags",
    "flat_tags": ".packtags",
    "Store": ".persistence",
    "StoreError": ".persistence",
    "Answer": ".reasons",
    "Reason": ".reasons",
    "CommandRequest": ".requests",
    "CompleteReport": ".requests",
    "ModeRequest": ".requests",
    "Transition": ".unit",
    "Trigger": ".unit",
    "Unit": ".unit",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    loaded = importlib.import_module(module, __name__)
    value = loaded if module == f".{name}" else getattr(loaded, name)
    globals()[name] = value
    return value


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
