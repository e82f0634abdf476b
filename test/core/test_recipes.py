"""Issue 32: recipes in the cell file, the changeover workflow in the engine (apply, refusal and
rollback, timeout), its guards, persistence across a restart, snapshot and input-log replay."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from packml_ros2.core import Cmd as C
from packml_ros2.core import ConfigError, Reason, State, Store, Unit, inputlog, parse_cell, snapshot
from packml_ros2.core.recipes import EmAnswer, ParamType

from .helpers import FakeClock, cell_unit

S = State
EMS = ["robot", "gripper", "vision"]
RECIPES: list[dict[str, Any]] = [
    {
        "id": 1,
        "name": "cola 0.5",
        "unit": "bottles",
        "primary_qty": 1200,
        "process_variables": [
            {
                "id": 1,
                "name": "fill",
                "unit": "ml",
                "type": "real",
                "value": 500,
                "min": 490,
                "max": 510,
            },
            {"id": 2, "name": "label", "type": "string", "value": "COLA"},
        ],
        "ingredients": [
            {
                "ingredient_id": 7,
                "parameters": [{"id": 1, "name": "syrup", "type": "lreal", "value": 0.12}],
            }
        ],
    },
    {
        "id": 2,
        "name": "water 1.0",
        "process_variables": [
            {"id": 1, "name": "fill", "unit": "ml", "type": "real", "value": 1000},
            {"id": 3, "name": "caps", "type": "dint", "value": 4},
        ],
    },
]
UNIT: dict[str, Any] = {
    "equipment_modules": {em: {} for em in EMS},
    "recipes": RECIPES,
    "recipe_timeout": 30,
    "remote_commands_enabled": True,
}


def make(clock: FakeClock, store: Store | None = None, **extra: Any) -> Unit:
    unit = Unit(cell_unit({**UNIT, **extra}), clock, store)
    for em in EMS:
        assert unit.em_seen(em).accepted
    return unit


def order(unit: Unit) -> int:
    c = unit.recipes.changeover
    assert c is not None
    return c.order


def orders(unit: Unit) -> list[tuple[int, int, int, tuple[str, ...]]]:
    """The changeover orders the unit output: (order, phase, recipe ID, EMs)."""
    return [
        (o, p, r.id, ems)
        for kind, (o, p, r, ems) in ((k, v) for k, v in unit.drain() if k == "recipe")
    ]


def test_the_cell_file_gives_typed_recipes() -> None:
    book = cell_unit(UNIT).recipes
    cola = book.find(0, "COLA 0.5")
    assert cola is not None and cola.id == 1 and cola.primary_qty == 1200
    assert [p.type for p in cola.process_variables] == [ParamType.REAL, ParamType.STRING]
    assert cola.parameter("fill") == 500 and cola.parameter("label") == "COLA"
    assert cola.parameter("syrup", ingredient=7) == 0.12
    assert book.find(2) is not None and book.find(2).parameter("caps") == 4  # type: ignore[union-attr]
    assert book.states == {S.STOPPED, S.IDLE, S.COMPLETE} and book.timeout == 30


@pytest.mark.parametrize(
    ("recipes", "where", "words"),
    [
        (
            [{"id": 1, "process_variables": [{"id": 1, "type": "real", "value": 600, "max": 510}]}],
            "value",
            "outside",
        ),
        ([{"id": 1, "process_variables": [{"id": 1, "type": "dint", "value": 1.5}]}], "value", ""),
        (
            [{"id": 1, "process_variables": [{"id": 1, "type": "dint", "value": 2**31}]}],
            "value",
            "",
        ),
        ([{"id": 1, "process_variables": [{"id": 1, "type": "float64"}]}], "type", ""),
        (
            [{"id": 1, "process_variables": [{"id": 1, "type": "string", "value": "x", "max": 3}]}],
            "process_variables[0]",
            "no min",
        ),
        ([{"id": 1}, {"id": 1}], "recipes[1]", "twice"),
        ([{"id": 1, "name": "A"}, {"id": 2, "name": "a"}], "recipes[1]", "also recipe 1"),
        ([{"id": 0}], "id", ""),
        ([{"name": "no id"}], "recipes[0]", "needs an id"),
        ([{"id": 1, "colour": "red"}], "colour", "unknown key"),
    ],
)
def test_bad_recipes_are_refused_with_their_path(recipes: Any, where: str, words: str) -> None:
    doc = {"cell": "c", "units": {"u": {"persistence": False, "recipes": recipes}}}
    with pytest.raises(ConfigError) as err:
        parse_cell(doc)
    text = str(err.value)
    assert where in text and words in text, text


def test_recipe_dir_and_settings(tmp_path: Path) -> None:
    (tmp_path / "recipes").mkdir()
    (tmp_path / "recipes" / "a.yaml").write_text("id: 5\nname: juice\n")
    (tmp_path / "recipes" / "b.yaml").write_text("id: 6\nname: [not, text]\n")
    doc = {
        "cell": "c",
        "units": {
            "u": {
                "persistence": False,
                "recipe_dir": "recipes",
                "recipe_states": ["Idle"],
                "initial_recipe": 5,
            }
        },
    }
    with pytest.raises(ConfigError) as err:
        parse_cell(doc, base_dir=tmp_path)
    assert "b.yaml" in str(err.value) and "a.yaml" not in str(err.value)
    (tmp_path / "recipes" / "b.yaml").write_text("id: 6\nname: milk\n")
    book = parse_cell(doc, base_dir=tmp_path).units["u"].recipes
    assert sorted(book.recipes) == [5, 6] and book.states == {S.IDLE} and book.initial == 5
    unit = Unit(parse_cell(doc, base_dir=tmp_path).units["u"], FakeClock())
    assert unit.status().recipe_current == 5 and unit.status().recipe_current_name == "juice"


def test_a_changeover_asks_every_em_and_commits_when_all_accept() -> None:
    clock = FakeClock()
    unit = make(clock)
    unit.drain()
    answer = unit.set_recipe(1, "", "operator")
    assert answer.accepted and "3 EM" in answer.message
    n = order(unit)
    assert orders(unit) == [(n, 1, 1, tuple(EMS))]
    view = unit.status()
    assert view.recipe_change_in_process and view.recipe_requested == 1
    assert view.recipe_current == 0
    assert {e.name: e.recipe_answer for e in view.equipment} == dict.fromkeys(EMS, 1)
    # while it runs: commands other than Stop/Abort, mode changes and another recipe wait
    refused = unit.command(C.RESET)
    assert not refused.accepted and refused.reason is Reason.RECIPE_CHANGE_IN_PROCESS
    assert unit.state is S.STOPPED
    assert unit.set_mode("maintenance").reason is Reason.RECIPE_CHANGE_IN_PROCESS
    assert unit.set_recipe(2).reason is Reason.RECIPE_CHANGE_IN_PROCESS
    clock.advance(2.0)
    for em in EMS:
        assert unit.em_recipe(em, n, True).accepted
    view = unit.status()
    assert not view.recipe_change_in_process and view.recipe_current == 1
    assert view.recipe_current_name == "cola 0.5" and "applied in 2.0 s" in view.recipe_result
    assert {e.name: e.recipe_answer for e in view.equipment} == dict.fromkeys(EMS, 2)
    assert unit.command(C.RESET).accepted  # the guard is gone
    events = [e.message for e in unit.admin().alarm_history]
    assert any("recipe change to 1 'cola 0.5' requested by operator" in m for m in events)


def test_one_refusal_rolls_every_em_back_and_refuses_the_changeover() -> None:
    clock = FakeClock()
    unit = make(clock)
    assert unit.set_recipe(1).accepted
    n = order(unit)
    for em in EMS:
        unit.em_recipe(em, n, True)
    assert unit.set_recipe(0, "water 1.0").accepted
    apply = order(unit)
    unit.drain()
    assert unit.em_recipe("robot", apply, True).accepted
    assert unit.em_recipe("gripper", apply, False, "fingers for 1.0 l not fitted").accepted
    back = order(unit)
    assert back == apply + 1
    assert orders(unit) == [(back, 2, 1, tuple(EMS))]  # rollback: recipe 1 again, to every EM
    assert unit.em_recipe("vision", apply, True).reason is Reason.NOTHING_TO_DO  # stale
    assert unit.status().recipe_change_in_process
    for em in EMS:
        assert unit.em_recipe(em, back, True).accepted
    view = unit.status()
    assert view.recipe_current == 1 and not view.recipe_change_in_process
    assert "refused: EM gripper refused it: fingers for 1.0 l not fitted" in view.recipe_result
    assert "rolled back to 1 'cola 0.5'" in view.recipe_result
    shown = {e.name: (e.recipe_answer, e.recipe_message) for e in view.equipment}
    assert shown == {
        "robot": (EmAnswer.ACCEPTED, ""),
        "vision": (EmAnswer.ACCEPTED, ""),
        "gripper": (EmAnswer.REFUSED, "fingers for 1.0 l not fitted"),
    }


def test_no_answer_within_the_timeout_is_a_refusal() -> None:
    clock = FakeClock()
    unit = make(clock)
    assert unit.set_recipe(2).accepted
    n = order(unit)
    unit.em_recipe("robot", n, True)
    unit.em_recipe("gripper", n, True)
    clock.advance(30.5)
    unit.advance()
    c = unit.recipes.changeover
    assert c is not None and c.order == n + 1
    assert "vision refused it: no answer within 30 s" in c.refusal
    clock.advance(31.0)
    unit.advance()
    view = unit.status()
    assert not view.recipe_change_in_process and view.recipe_current == 0
    assert "not by robot, gripper, vision" in view.recipe_result


def test_an_em_lost_during_a_changeover_refuses_it_at_once() -> None:
    """Not at the changeover's timeout: the lost EM cannot answer, and while the changeover runs
    the unit refuses Reset (an operator would wait out ``recipe_timeout``)."""
    clock = FakeClock()
    unit = make(clock)
    assert unit.set_recipe(2).accepted
    n = order(unit)
    assert unit.em_recipe("robot", n, True).accepted
    assert unit.em_lost("gripper", "left").accepted  # (its reaction: the unit aborts)
    c = unit.recipes.changeover
    assert c is not None and c.order == n + 1, "rolled back at once"
    assert c.refusal == "EM gripper refused it: lost (left)"
    for em in ("robot", "vision"):
        assert unit.em_recipe(em, n + 1, True).accepted
    view = unit.status()
    assert not view.recipe_change_in_process and view.recipe_current == 0
    assert "not by gripper: lost (left)" in view.recipe_result


def test_an_em_lost_during_a_rollback_ends_it() -> None:
    clock = FakeClock()
    unit = make(clock)
    assert unit.set_recipe(2).accepted
    n = order(unit)
    assert unit.em_recipe("gripper", n, False, "wrong fingers").accepted
    assert unit.em_recipe("robot", n + 1, True).accepted
    assert unit.em_recipe("gripper", n + 1, True).accepted
    assert unit.em_lost("vision", "no report for 2 s").accepted
    view = unit.status()
    assert not view.recipe_change_in_process, "no answer awaited from a lost EM"
    assert "not by vision: lost (no report for 2 s)" in view.recipe_result


def test_a_recipe_change_in_execute_is_refused_with_its_reason() -> None:
    clock = FakeClock()
    unit = Unit(cell_unit({"recipes": RECIPES}), clock)
    assert unit.command(C.RESET).accepted and unit.command(C.START).accepted
    assert unit.state is S.EXECUTE
    answer = unit.set_recipe(2)
    assert not answer.accepted and answer.reason is Reason.RECIPE_NOT_ALLOWED
    assert "EXECUTE" in answer.message and "only in STOPPED, IDLE, COMPLETE" in answer.message
    assert unit.status().recipe_requested == 0 and not unit.status().recipe_change_in_process
    unknown = unit.set_recipe(9)
    assert unknown.reason is Reason.RECIPE_UNKNOWN and "1 'cola 0.5'" in unknown.message
    assert unit.command(C.STOP).accepted and unit.state is S.STOPPED
    assert unit.set_recipe(2).accepted and unit.status().recipe_current == 2  # no EMs: at once


def test_stop_and_abort_pass_a_changeover() -> None:
    clock = FakeClock()
    unit = make(clock)
    assert unit.set_recipe(1).accepted
    assert unit.command(C.ABORT).accepted
    assert unit.status().recipe_change_in_process


def test_the_current_recipe_survives_a_restart(tmp_path: Path) -> None:
    path = tmp_path / "u.sqlite3"
    clock = FakeClock()
    unit = make(clock, Store(path, "u"))
    assert unit.set_recipe(2).accepted
    n = order(unit)
    for em in EMS:
        unit.em_recipe(em, n, True)
    assert unit.status().recipe_current == 2
    assert unit.store is not None
    unit.store.close()  # not unit.close(), which saves a snapshot: the journal must have it
    again = Unit(cell_unit(UNIT), clock, Store(path, "u"))
    assert again.status().recipe_current == 2 and again.status().recipe_current_name == "water 1.0"


def test_snapshot_and_input_log_replay_give_the_same_changeover() -> None:
    clock = FakeClock()
    unit = make(clock)
    log: list[tuple[float, str, dict[str, Any]]] = []
    unit.on_input = lambda t, name, fields: log.append((t, name, fields))
    assert unit.set_recipe(1).accepted
    n = order(unit)
    unit.em_recipe("robot", n, True)
    unit.drain()
    doc = snapshot.capture(unit)
    again = snapshot.restore(cell_unit(UNIT), clock, doc)
    for em in ("gripper", "vision"):
        assert again.em_recipe(em, n, True).accepted
        unit.em_recipe(em, n, True)
    assert again.status().recipe_current == unit.status().recipe_current == 1
    assert [name for _, name, _ in log] == ["recipe", "em.recipe", "em.recipe", "em.recipe"]
    replayed = make(FakeClock())
    for _, name, fields in log:
        replayed.apply_input(name, fields)
    assert replayed.status().recipe_current == 1
    assert inputlog.INPUTS["em.recipe"].name in inputlog.EM_INPUTS


def test_em_answers_are_shown_per_em() -> None:
    unit = make(FakeClock())
    assert unit.set_recipe(1).accepted
    n = order(unit)
    assert unit.em_recipe("robot", n, True).accepted
    assert unit.status().equipment[0].recipe_answer == EmAnswer.ACCEPTED
    unit.em_recipe("vision", n, False, "camera  program\nmissing")
    c = unit.recipes.changeover
    assert c is not None and c.refusal == "EM vision refused it: camera program missing"
    assert all(e.recipe_answer == EmAnswer.PENDING for e in unit.status().equipment)
    vision = next(e for e in unit.status().equipment if e.name == "vision")
    assert vision.recipe_message == "camera program missing"
