"""Issue 32: recipes through the HMI's API, against a real unit node over real DDS (as
test_bridge.py): the unit's recipes in /api/config and GET /api/units/{unit}/recipes, the recipe
fields, the stack light and each EM's answer in the status the page gets, ``POST
/api/units/{unit}/set_recipe`` forwarded with source ``hmi:<user>`` at the maintenance level, the
unit's refusals (reason code and message) passed on, and hostile bodies refused here (4xx with a
reason code) with nothing reaching the unit.

The unit's one EM is inactive: a changeover asks no EM and applies at once (the EMs' part is
test_recipe_browser.py's, with simulated EMs in `packml launch`). Every wait is on a condition."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from packml_ros2.hmi.access import UNIT_ACTION_LEVEL
from test.hmi import test_bridge
from test.hmi.test_bridge import UNIT, Cell, serving
from test.hmi.test_hmi_security import JSON, refused
from test.hmi.test_logins import login, users
from test.recipe_cell import RECIPES

pytestmark = pytest.mark.ros


@pytest.fixture
def make_cell(
    ros: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> Iterator[Callable[..., Cell]]:
    """test_bridge's cell, its unit with recipe_cell's two recipes (1 'cola 0.5' in use)."""
    doc = {**test_bridge.UNIT_DOC, "recipes": RECIPES, "initial_recipe": 1}
    monkeypatch.setattr(test_bridge, "UNIT_DOC", doc)
    made: list[Cell] = []

    def make(with_users: bool = False) -> Cell:
        made.append(Cell(ros, tmp_path, None, 3.0, users() if with_users else None))
        return made[-1]

    yield make
    for cell in made:
        cell.close()


def test_recipes_and_the_changeover_are_what_the_page_gets(make_cell: Any) -> None:
    cell = make_cell()
    assert UNIT_ACTION_LEVEL["set_recipe"] == "maintenance"  # at least a mode change's level
    with serving(cell.bridge) as http:
        config = http.get("/api/config").json()
        unit = config["units"][0]
        assert [(r["id"], r["name"]) for r in unit["recipes"]] == [
            (1, "cola 0.5"),
            (2, "water 1.0"),
        ]
        cola = unit["recipes"][0]
        assert cola["unit"] == "bottles" and cola["primary_qty"] == 1200
        assert cola["process_variables"][1] == {
            "id": 2,
            "name": "label",
            "unit": "",
            "type": "string",
            "value": 0.0,
            "text": "COLA-500",
        }
        assert cola["ingredients"][0]["parameters"][0]["type"] == "lreal"
        assert unit["recipe_states"] == ["STOPPED", "IDLE", "COMPLETE"]
        assert config["unit_action_level"]["set_recipe"] == "maintenance"

        status = http.get("/api/snapshot").json()["units"][UNIT]["status"]
        assert (status["recipe_current"], status["recipe_current_name"]) == (1, "cola 0.5")
        assert status["recipe_change_in_process"] is False and status["recipe_requested"] == 0
        light = status["stack_light"]  # the default preset (omac): amber on in Stopped
        assert light["colors"] == ["red", "amber", "green", "blue"]
        assert light["modes"] == [0, 1, 0, 0] and light["horn"] is False
        em = status["equipment_modules"][0]
        assert (em["recipe_answer"], em["recipe_answer_name"], em["recipe_message"]) == (
            0,
            "none",
            "",
        )
        assert cell.bridge.snapshot()["units"][UNIT]["why"]["recipe"] == ""

        # a change: forwarded with source hmi:anyone, the unit's answer passed on
        mark = len(cell.events)
        answer = http.post(f"/api/units/{UNIT}/set_recipe", json={"recipe_id": 2})
        assert answer.status_code == 200 and answer.json()["accepted"], answer.text
        assert "recipe 2 'water 1.0' applied" in answer.json()["message"]
        now = cell.wait_status(lambda s: s["recipe_current"] == 2, "recipe 2 in use", mark)
        assert now["recipe_current_name"] == "water 1.0"
        assert "recipe 2 'water 1.0' applied" in now["recipe_result"]
        # (the unit's own status, as another subscriber gets it)
        cell.client.status.wait_for(lambda s: s.recipe_current == 2, 10.0, "recipe 2 in use")
        mark = len(cell.events)  # (recipe 1 was in use before: only a status after counts)
        by_name = http.post(f"/api/units/{UNIT}/set_recipe", json={"recipe_name": "cola 0.5"})
        assert by_name.json()["accepted"], by_name.text
        cell.wait_status(lambda s: s["recipe_current"] == 1, "recipe 1 by its name", mark)
        listing = http.get(f"/api/units/{UNIT}/recipes").json()
        assert [r["id"] for r in listing["recipes"]] == [1, 2]
        assert (
            listing["recipe_current"] == 1 and listing["equipment_modules"][0]["name"] == "nozzle"
        )
        assert http.get("/api/units/capper/recipes").status_code == 404

        # the unit's refusals come back with their reason code and message (200)
        unknown = http.post(f"/api/units/{UNIT}/set_recipe", json={"recipe_id": 9})
        assert unknown.status_code == 200 and unknown.json()["result_name"] == "RECIPE_UNKNOWN"
        assert "recipe 9 is not one of filler's recipes" in unknown.json()["message"]
        for command, state in (("reset", "IDLE"), ("start", "EXECUTE")):
            assert cell.bridge.act_sync(UNIT, "command", {"command": command})["accepted"]
            last = cell.wait_status(lambda s, st=state: s["state_name"] == st, state)
        assert last["stack_light"]["modes"] == [0, 0, 1, 0]  # green on in Execute
        reason = cell.bridge.snapshot()["units"][UNIT]["why"]["recipe"]
        assert reason == (
            "not in EXECUTE (PRODUCTION): filler changes its recipe only in STOPPED, IDLE, COMPLETE"
        )
        in_execute = http.post(f"/api/units/{UNIT}/set_recipe", json={"recipe_id": 2})
        body = in_execute.json()
        assert in_execute.status_code == 200 and body["result_name"] == "RECIPE_NOT_ALLOWED", body
        assert (
            "refused in EXECUTE" in body["message"] and cell.client.status.last.recipe_current == 1
        )


@pytest.mark.parametrize(
    "body",
    [
        {"recipe_id": "2"},
        {"recipe_id": 2.0},
        {"recipe_id": True},
        {"recipe_id": 0},
        {"recipe_id": -1},
        {"recipe_id": 2**31},
        {"recipe_id": 2**32 + 2},  # no wrap-around to recipe 2
        {"recipe_id": [2]},
        {"recipe_name": ""},
        {"recipe_name": "   "},
        {"recipe_name": "w" * 256},
        {"recipe_name": "x" * 60_000},
        {"recipe_name": "water\x001.0"},
        {"recipe_name": {"$ne": ""}},
        {"recipe_id": 2, "recipe_name": "water 1.0"},  # one of them
        {},
        {"recipe_id": 2, "source": "local:panel"},  # no caller-chosen source
    ],
)
def test_hostile_set_recipe_bodies_are_refused_and_nothing_is_sent(
    make_cell: Any, body: dict[str, Any]
) -> None:
    cell = make_cell()
    before = cell.client.status.last
    with serving(cell.bridge) as http:
        r = http.post(f"/api/units/{UNIT}/set_recipe", content=json.dumps(body), headers=JSON)
        answer = refused(r, 400, "BAD_ARGUMENT")
        assert answer["result_name"] == "INVALID_ARGUMENT" and len(answer["message"]) < 400
        assert "recipe" in answer["message"] or "source" in answer["message"], answer
        # the unit still answers, and nothing of the above reached it
        ok = http.post(f"/api/units/{UNIT}/set_recipe", json={"recipe_id": 9})
        assert ok.json()["result_name"] == "RECIPE_UNKNOWN", ok.text
    after = cell.client.status.last
    assert (after.recipe_current, after.recipe_changeover) == (
        before.recipe_current,
        before.recipe_changeover,
    )


@pytest.mark.parametrize(
    ("content", "code"),
    [
        (b'{"recipe_id": 2', "MALFORMED_JSON"),
        (b'{"recipe_id": NaN}', "MALFORMED_JSON"),
        (b'{"recipe_id": ' + b"9" * 5000 + b"}", "MALFORMED_JSON"),
        (b'{"recipe_id": 1, "recipe_id": 2}', "MALFORMED_JSON"),
    ],
)
def test_malformed_set_recipe_bodies_get_400(make_cell: Any, content: bytes, code: str) -> None:
    cell = make_cell()
    with serving(cell.bridge) as http:
        r = http.post(f"/api/units/{UNIT}/set_recipe", content=content, headers=JSON)
        refused(r, 400, code)
    assert cell.client.status.last.recipe_changeover == 0


def test_a_recipe_change_needs_the_maintenance_level(make_cell: Any) -> None:
    cell = make_cell(with_users=True)
    with serving(cell.bridge) as http:
        anna = {"Authorization": f"Bearer {login(http, 'anna')}"}  # operator
        r = http.post(f"/api/units/{UNIT}/set_recipe", json={"recipe_id": 2}, headers=anna)
        body = refused(r, 403, "LEVEL_TOO_LOW")
        assert (
            body["message"]
            == "set_recipe needs the maintenance level: anna is logged in as operator"
        )
        assert cell.client.status.last.recipe_changeover == 0  # nothing reached the unit
        ben = {"Authorization": f"Bearer {login(http, 'ben')}"}  # maintenance
        mark = len(cell.events)
        ok = http.post(f"/api/units/{UNIT}/set_recipe", json={"recipe_id": 2}, headers=ben)
        assert ok.status_code == 200 and ok.json()["accepted"], ok.text
        cell.wait_status(lambda s: s["recipe_current"] == 2, "recipe 2", mark)
        nobody = http.post(f"/api/units/{UNIT}/set_recipe", json={"recipe_id": 1})
        refused(nobody, 403, "LOGIN_REQUIRED")
