"""Issue 32: the OPC 30050 v2 draft's Status members and the recipe change through OPC UA, as
node-opcua (test/opcua_client/client.mjs) sees them on issue 32's recipe cell (test/recipe_cell.py:
unit ``filler``, EMs robot, gripper, vision) run by ``packml launch``, with ``packml opcua``.

- StateCurrent, StackLight (+ Colors), EquipmentInterlock {Blocked, Starved}, RecipeCurrent,
  RecipeRequested, RecipeChangeInProcess live in the server's own namespace (the PackML
  namespace keeps the official v1.01 model); the recipes are plain typed nodes.
- SetRecipe(SelectedRecipe) with the gripper's ``wrong_fingers`` fault on (``packml fault``): a
  Good answer (the request is accepted), RecipeChangeInProcess true then false, RecipeCurrent
  stays 1 (rolled back) and RecipeResult says why; again: RecipeCurrent becomes 2.
- In Execute SetRecipe is refused (BadInvalidState, RECIPE_NOT_ALLOWED) and changes nothing; an
  unknown recipe is BadNotFound; an anonymous session is refused like every other method.

Every wait is on a condition (a subscription of the client, a line of output), never a fixed
sleep.
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from typing import Any

import pytest
import yaml

from packml_ros2.core.stacklight import Shown, encode_opcua
from packml_ros2.opcua.config import hash_password
from packml_ros2.testing.processes import Processes, wait_until
from test.opcua.test_opcua import PASSWORD, NodeClient, free_port, start_face
from test.recipe_cell import REFUSAL, recipe_cell
from test.ros.cells import UnitClient

pytestmark = pytest.mark.ros

CELL = "recipe_face"
UNIT = "P:PackMLObjects/U:filler"
STATUS = f"{UNIT}/P:Status"
MS = f"{UNIT}/P:BaseStateMachine/P:MachineState"
ES = f"{MS}/P:ExecuteState"
RECIPES = f"{STATUS}/U:Recipe"
PV1 = f"{RECIPES}/U:Recipe_1/U:ProcessVariables"
PV2 = f"{RECIPES}/U:Recipe_2/U:ProcessVariables"
SYRUP = f"{RECIPES}/U:Recipe_1/U:Ingredients/U:Ingredient_7/U:Parameter_LREAL/U:syrup_ratio"


class Face:
    def __init__(self, url: str, client: NodeClient) -> None:
        self.url, self.client = url, client

    def anonymous(self, steps: list[dict[str, Any]]) -> list[dict[str, Any]]:
        return _no_errors(self.client.job(self.url, steps))

    def operator(self, steps: list[dict[str, Any]], timeout: float = 60.0) -> list[dict[str, Any]]:
        user = {"name": "operator", "password": PASSWORD}
        return _no_errors(self.client.job(self.url, steps, timeout, user=user))


def _no_errors(results: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Every step ran (a path that does not resolve, a wait that timed out: its error)."""
    failed = [r["error"] for r in results if "error" in r]
    assert not failed, failed
    return results


@pytest.fixture(scope="module")
def face(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Face]:
    tmp = tmp_path_factory.mktemp("opcua_recipes")
    port = free_port()
    doc = recipe_cell(CELL)
    doc["opcua"] = {
        "port": port,
        "users": {"operator": hash_password(PASSWORD, iterations=1000)},
        "security_policies": ["None"],
        "state_dir": str(tmp / "state"),
    }
    path = tmp / f"{CELL}.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    (tmp / "logs").mkdir()
    procs = Processes(tmp / "logs")
    client = NodeClient(tmp / "logs" / "node_client.log", tmp / "pki")
    try:
        launch = procs.module("launch", "packml_ros2.cli.main", "launch", str(path))
        wait_until(lambda: "is up" in launch.output() or not launch.running(), 60, 0.05, "the cell")
        assert launch.running(), launch.output()
        client.wait_ready()
        start_face(procs, path)
        yield Face(f"opc.tcp://127.0.0.1:{port}/", client)
    finally:
        client.close()
        failures = procs.close()
        assert not failures, failures


def _wait(path: str, value: Any, timeout: int = 20000) -> dict[str, Any]:
    return {"op": "wait", "path": path, "value": value, "timeout": timeout}


#: RecipeChangeInProcess was true, and is false now
WENT_AND_ENDED = "seen.includes(true) && seen.indexOf(true) < seen.length - 1 && !seen.at(-1)"


def test_v2_draft_status_members_and_the_recipes(face: Face, ros: Any) -> None:
    filler = UnitClient(ros, CELL, "filler")
    filler.ready()
    (
        state,
        status,
        interlock,
        blocked,
        starved,
        light,
        colors,
        current,
        requested,
        changing,
        recipes,
        recipe,
        name,
        qty,
        fill,
        fill_unit,
        label,
        valves,
        syrup,
        arguments,
    ) = face.anonymous(
        [
            _wait(f"{STATUS}/U:RecipeCurrent", 1),
            {"op": "browse", "path": STATUS},
            {"op": "browse", "path": f"{STATUS}/U:EquipmentInterlock"},
            {"op": "read", "path": f"{STATUS}/U:EquipmentInterlock/U:Blocked"},
            {"op": "read", "path": f"{STATUS}/U:EquipmentInterlock/U:Starved"},
            {"op": "read", "path": f"{STATUS}/U:StackLight"},
            {"op": "read", "path": f"{STATUS}/U:StackLight/U:Colors"},
            {"op": "read", "path": f"{STATUS}/U:RecipeCurrent"},
            {"op": "read", "path": f"{STATUS}/U:RecipeRequested"},
            {"op": "read", "path": f"{STATUS}/U:RecipeChangeInProcess"},
            {"op": "browse", "path": RECIPES},
            {"op": "browse", "path": f"{RECIPES}/U:Recipe_1"},
            {"op": "read", "path": f"{RECIPES}/U:Recipe_1/U:Name"},
            {"op": "read", "path": f"{RECIPES}/U:Recipe_1/U:PrimaryQty"},
            {"op": "read", "path": f"{PV1}/U:Parameter_REAL/U:fill_volume"},
            {"op": "read", "path": f"{PV1}/U:Parameter_REAL/U:fill_volume/U:Unit"},
            {"op": "read", "path": f"{PV2}/U:Parameter_STRING/U:label"},
            {"op": "read", "path": f"{PV2}/U:Parameter_DINT/U:valves"},
            {"op": "read", "path": SYRUP},
            {"op": "read", "path": f"{UNIT}/U:SetRecipe/0:InputArguments"},
        ]
    )
    assert state["value"] == 1
    # the v2 draft's names in the server's own namespace (1), none in the PackML one: the
    # PackML namespace holds the v1.01 model only (its EquipmentBlocked/Starved stay)
    names = set(status["names"])
    draft = {
        "StateCurrent",
        "StackLight",
        "EquipmentInterlock",
        "RecipeCurrent",
        "RecipeRequested",
        "RecipeChangeInProcess",
        "RecipeResult",
        "Recipe",
    }
    assert {f"1:{n}" for n in draft} <= names, names
    assert not {n for n in names if n.split(":", 1)[1] in draft and not n.startswith("1:")}
    assert {n.split(":", 1)[1] for n in names} >= {"EquipmentBlocked", "EquipmentStarved"}
    assert set(interlock["names"]) == {"1:Blocked", "1:Starved"}
    assert blocked["value"] is False and starved["value"] is False
    # StackLight follows the unit's status: the encoding of what the ROS message shows
    shown = filler.status.last.stack_light
    assert colors["value"] == list(shown.colors) and len(colors["value"]) > 0
    assert light["value"] == encode_opcua(Shown(tuple(shown.modes), shown.horn))
    assert light["status"] == "Good" and any(light["value"])  # Stopped lights something
    assert current["value"] == 1 and changing["value"] is False
    assert requested["status"] == "Good" and requested["value"] in (0, 1)
    assert set(recipes["names"]) == {"1:Recipe_1", "1:Recipe_2"}
    assert {
        "1:ID",
        "1:Name",
        "1:Unit",
        "1:PrimaryQty",
        "1:ProcessVariables",
        "1:Ingredients",
    } <= set(recipe["names"])
    assert name["value"] == "cola 0.5" and qty["value"] == 1200
    assert fill["value"] == 500 and fill_unit["value"] == "ml"
    assert label["value"] == "AQUA-1000" and valves["value"] == 8 and syrup["value"] == 12.5
    assert [(a["Name"], a["ValueRank"]) for a in arguments["value"]] == [("SelectedRecipe", -1)]


def test_set_recipe_rolls_back_once_then_changes_and_is_refused_in_execute(face: Face) -> None:
    # anonymous sessions are read-only: refused like every other method, nothing changes
    anonymous, user_executable = face.anonymous(
        [
            {"op": "call", "path": f"{UNIT}/U:SetRecipe", "args": [{"type": "Int32", "value": 2}]},
            {"op": "read", "path": f"{UNIT}/U:SetRecipe", "attribute": "UserExecutable"},
        ]
    )
    assert anonymous["status"] == "BadUserAccessDenied", anonymous
    assert user_executable["value"] is False
    # the gripper refuses the next recipe once (the CLI, as an operator would)
    fault = subprocess.run(
        [
            sys.executable,
            "-m",
            "packml_ros2.cli.main",
            "fault",
            f"{CELL}/filler/gripper",
            "wrong_fingers",
            "on",
        ],
        check=False,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert fault.returncode == 0, fault.stdout + fault.stderr
    _, current_before, _, _, refused_change, changing, current, result, requested = face.operator(
        [
            _wait(f"{STATUS}/U:StateCurrent", 2),
            {"op": "watch", "path": f"{STATUS}/U:RecipeCurrent", "name": "current"},
            {"op": "watch", "path": f"{STATUS}/U:RecipeChangeInProcess", "name": "changing"},
            {"op": "watch", "path": f"{STATUS}/U:RecipeResult", "name": "result"},
            {"op": "call", "path": f"{UNIT}/U:SetRecipe", "args": [{"type": "Int32", "value": 2}]},
            {"op": "watched", "name": "changing", "until": WENT_AND_ENDED, "timeout": 30000},
            {"op": "read", "path": f"{STATUS}/U:RecipeCurrent"},
            {"op": "watched", "name": "result", "until": f"seen.at(-1).includes({REFUSAL!r})"},
            {"op": "read", "path": f"{STATUS}/U:RecipeRequested"},
        ]
    )
    assert current_before["value"] == 1
    assert refused_change["status"] == "Good", refused_change  # accepted as a request
    assert changing["seen"][0] is False and changing["seen"][-1] is False
    assert current["value"] == 1, (current, result)  # rolled back
    assert "gripper" in result["seen"][-1], result
    assert requested["status"] == "Good"
    # again, the fault spent: the changeover goes through
    call, changing, current, unknown, still = face.operator(
        [
            {"op": "watch", "path": f"{STATUS}/U:RecipeChangeInProcess", "name": "changing"},
            {"op": "call", "path": f"{UNIT}/U:SetRecipe", "args": [{"type": "Int32", "value": 2}]},
            {"op": "watched", "name": "changing", "until": WENT_AND_ENDED, "timeout": 30000},
            _wait(f"{STATUS}/U:RecipeCurrent", 2),
            {"op": "call", "path": f"{UNIT}/U:SetRecipe", "args": [{"type": "Int32", "value": 99}]},
            {"op": "read", "path": f"{STATUS}/U:RecipeChangeInProcess"},
        ]
    )[1:]
    assert call["status"] == "Good", call
    assert current["value"] == 2
    assert unknown["status"] == "BadNotFound", unknown
    assert unknown["diagnostics"]["symbolicId"] == "RECIPE_UNKNOWN"
    assert still["value"] is False
    # in Execute a changeover is not allowed: a Bad status with the unit's reason; nothing changes
    (reset, _, start, _, in_execute, zero, current, changing, stop, _) = face.operator(
        [
            {"op": "call", "path": f"{MS}/P:Reset"},
            _wait(f"{STATUS}/U:StateCurrent", 4),
            {
                "op": "call",
                "path": f"{ES}/P:Start",
                "args": [
                    {"type": "ExtensionObject", "dataType": "P:i=16", "array": True, "value": []}
                ],
            },
            _wait(f"{STATUS}/U:StateCurrent", 6),
            {"op": "call", "path": f"{UNIT}/U:SetRecipe", "args": [{"type": "Int32", "value": 1}]},
            {"op": "call", "path": f"{UNIT}/U:SetRecipe", "args": [{"type": "Int32", "value": 0}]},
            {"op": "read", "path": f"{STATUS}/U:RecipeCurrent"},
            {"op": "read", "path": f"{STATUS}/U:RecipeChangeInProcess"},
            {"op": "call", "path": f"{MS}/P:Stop"},
            _wait(f"{STATUS}/U:StateCurrent", 2),
        ]
    )
    assert reset["status"] == start["status"] == stop["status"] == "Good"
    assert in_execute["status"] == "BadInvalidState", in_execute
    assert in_execute["diagnostics"]["symbolicId"] == "RECIPE_NOT_ALLOWED"
    assert in_execute["diagnostics"]["localizedText"]
    assert zero["status"] == "BadInvalidArgument" and zero["inputArgumentResults"] == [
        "BadOutOfRange"
    ]
    assert current["value"] == 2 and changing["value"] is False
