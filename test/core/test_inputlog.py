"""The input log's schema (core/inputlog.py): every engine input is logged under its schema name
and fields, a log applied to a fresh unit reproduces the outputs, and schema 0 (the engine's
method and argument names, before the schema had a number) is read too."""

from __future__ import annotations

from typing import Any

import pytest

from packml_ros2.core import Cmd as C
from packml_ros2.core import CommandRequest, CompleteReport, ModeRequest, State, Unit, inputlog
from packml_ros2.core.config import Descriptor, Ingredient, Product

from .helpers import FakeClock, cell_unit

UNIT = {
    "equipment_modules": {"em1": {}},
    "alarms": [{"id": 7, "message": "jam", "category": 6}],
    "counters": {"processed": [{"id": 1}]},
    "remote_commands_enabled": True,
    "recipes": [
        {"id": 1, "name": "a", "process_variables": [{"id": 1, "type": "dint", "value": 3}]}
    ],
}


def drive_every_input(unit: Unit, clock: FakeClock) -> None:
    """One of every input (and a few steps of the state machine)."""
    unit.em_seen("em1")
    unit.command(C.RESET, "remote:line")
    unit.em_complete("em1", unit.state, unit.sequence)
    unit.command(C.START)
    unit.step([CompleteReport("em1", State.STARTING, unit.sequence), CommandRequest(C.HOLD),
               ModeRequest("manual")])  # fmt: skip
    clock.advance(0.5)
    unit.advance()
    clock.advance(-30.0)  # the wall clock steps back (NTP): the log's one stamp that goes back
    unit.clock_step(-30.0)
    unit.em_interlock("em1", True, False, 3)
    unit.em_count("em1", "processed", 0, 4)
    unit.set_alarm(7, 0, True, "operator")
    unit.ack_alarms(7, 0)
    unit.set_alarm(7, 0, False)
    unit.reset_alarms(True)
    unit.set_mach_speed(12.5)
    unit.set_parameters([Descriptor(1, "speed", "m/s", 2.0)])
    unit.set_product([Product(3, (Descriptor(1, "t", "C", 80.0),), (Ingredient(5, ()),))])
    unit.set_remote_enabled(False)
    unit.set_interlock(True, "downstream blocked", "coordinator")
    unit.command(C.STOP)
    unit.em_complete("em1", unit.state, unit.sequence)
    unit.set_mode("maintenance")
    unit.em_complete("em1", unit.state, unit.sequence)
    assert unit.set_recipe(1, "", "operator").accepted
    assert unit.em_recipe("em1", unit.recipes.order, True).accepted
    unit.set_em_active("em1", False)
    unit.reset_times(all_times=False)
    unit.reset_counters()
    unit.em_lost("em1", "left")
    unit.shutdown("SIGINT")


def recorded() -> tuple[list[tuple[float, str, dict[str, Any]]], list[Any]]:
    clock = FakeClock()
    unit = Unit(cell_unit(UNIT), clock)
    log: list[tuple[float, str, dict[str, Any]]] = []
    unit.on_input = lambda t, name, fields: log.append((t, name, fields))
    drive_every_input(unit, clock)
    return log, [x for kind, x in unit.drain() if kind == "transition"]


def test_every_input_is_logged_under_its_schema_name_and_fields() -> None:
    log, _ = recorded()
    names = {name for _, name, _ in log}
    # advance() is not logged: a replay fires deadlines at their own times (packml_ros2.driver)
    assert names == set(inputlog.INPUTS) - {"advance"}, set(inputlog.INPUTS) - names
    for _, name, fields in log:
        assert tuple(fields) == inputlog.INPUTS[name].fields, name


def test_a_log_applied_to_a_fresh_unit_gives_the_same_transitions() -> None:
    log, transitions = recorded()
    clock = FakeClock()
    again = Unit(cell_unit(UNIT), clock)
    for t, name, fields in log:
        clock.t = t
        inputlog.apply(again, name, fields)
    replayed = [x for kind, x in again.drain() if kind == "transition"]
    assert replayed == transitions
    assert len(transitions) >= 9


#: Schema 0 as the unit node wrote it: the engine's method names and argument names.
SCHEMA_0 = [
    ("em_seen", {"name": "em1"}),
    ("command", {"cmd": 1, "source": "operator"}),
    ("em_complete", {"name": "em1", "state": 15, "sequence": 2}),
    ("step", {"requests": [{"kind": "command", "cmd": 2, "source": "operator"},
                           {"kind": "mode", "mode": "manual", "source": "operator"},
                           {"kind": "complete", "em": "em1", "state": 4, "sequence": 3}]}),
    ("em_interlock", {"name": "em1", "blocked": True, "starved": False, "material": 0}),
    ("em_count", {"name": "em1", "kind": "processed", "index": 0, "increment": 2}),
    ("set_alarm", {"alarm_id": 7, "value": 0, "active": True, "source": "operator", "em": "",
                   "warning": None, "category": -1, "message": ""}),
    ("ack_alarms", {"alarm_id": None, "value": 0, "source": "operator"}),
    ("reset_alarms", {"clear_first_out": False, "source": "operator"}),
    ("set_mach_speed", {"speed": 3.0, "source": "operator"}),
    ("set_parameters", {"parameters": [{"id": 1, "name": "p", "unit": "", "value": 1.0}],
                        "source": "operator"}),
    ("set_product", {"products": [{"product_id": 2, "process_variables": [], "ingredients": []}],
                     "source": "operator"}),
    ("set_remote_enabled", {"enabled": True}),
    ("set_interlock", {"active": False, "reason": "", "source": "coordinator"}),
    ("set_mode", {"mode": 2, "source": "operator"}),
    ("set_em_active", {"name": "em1", "active": False, "source": "operator"}),
    ("reset_times", {"all_times": True, "source": "operator"}),
    ("reset_counters", {"source": "operator"}),
    ("em_lost", {"name": "em1", "detail": "no report for 2 s"}),
    ("advance", {}),
    ("shutdown", {"detail": "SIGINT"}),
]  # fmt: skip


def test_schema_0_is_upgraded_and_applies() -> None:
    assert inputlog.schema_of({"document": None, "time": 1.0}) == 0
    assert {name for name, _ in SCHEMA_0} == set(inputlog._SCHEMA_0)
    unit = Unit(cell_unit(UNIT), FakeClock())
    for name, fields in SCHEMA_0:
        new_name, new_fields = inputlog.upgrade(name, fields, 0)
        assert tuple(new_fields) == inputlog.INPUTS[new_name].fields
        inputlog.apply(unit, new_name, new_fields)  # every one is a valid engine input
    step = inputlog.upgrade(*SCHEMA_0[3], 0)[1]["requests"]
    assert [r["kind"] for r in step] == ["command", "mode", "state_complete"]
    assert step[0]["command"] == 2


def test_an_unknown_input_or_a_newer_schema_is_refused() -> None:
    with pytest.raises(ValueError, match="newer than this version"):
        inputlog.upgrade("command", {}, inputlog.SCHEMA + 1)
    with pytest.raises(ValueError, match="not an input of schema 0"):
        inputlog.upgrade("teleport", {}, 0)
    with pytest.raises(ValueError, match="not an engine input"):
        inputlog.apply(Unit(cell_unit({}), FakeClock()), "set_mode", {"mode": 2})
