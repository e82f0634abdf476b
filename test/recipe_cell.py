"""Issue 32's cell for the faces' tests: unit ``filler`` with three simulated EMs that take a
moment to change over, one (``gripper``) with a ``refuse_recipe`` fault that refuses the next
recipe once, two recipes and the ``changeover`` user mode. ``write_recipe_cell(tmp_path, cell)``
writes it; ``packml launch`` runs it (test/ros/test_launcher_cli.py: ``Launched``).

    packml fault <cell>/filler/gripper wrong_fingers on   # the next changeover is refused once
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

FAST = {"resetting": 0.1, "starting": 0.1, "stopping": 0.1, "clearing": 0.1, "aborting": 0.05}
RECIPES: list[dict[str, Any]] = [
    {
        "id": 1,
        "name": "cola 0.5",
        "unit": "bottles",
        "primary_qty": 1200,
        "process_variables": [
            {
                "id": 1,
                "name": "fill_volume",
                "unit": "ml",
                "type": "real",
                "value": 500.0,
                "min": 490.0,
                "max": 510.0,
            },
            {"id": 2, "name": "label", "type": "string", "value": "COLA-500"},
            {"id": 3, "name": "valves", "type": "dint", "value": 12},
        ],
        "ingredients": [
            {
                "ingredient_id": 7,
                "parameters": [
                    {"id": 1, "name": "syrup_ratio", "unit": "%", "type": "lreal", "value": 12.5}
                ],
            }
        ],
    },
    {
        "id": 2,
        "name": "water 1.0",
        "unit": "bottles",
        "primary_qty": 800,
        "process_variables": [
            {"id": 1, "name": "fill_volume", "unit": "ml", "type": "real", "value": 1000.0},
            {"id": 2, "name": "label", "type": "string", "value": "AQUA-1000"},
            {"id": 3, "name": "valves", "type": "dint", "value": 8},
        ],
    },
]
REFUSAL = "the fingers for this bottle are not in the rack"


def recipe_cell(cell: str) -> dict[str, Any]:
    """The cell file's document."""
    em = {"durations": FAST, "cycle_time": 0.2, "changeover_time": 0.3, "counter": "none"}
    return {
        "cell": cell,
        "units": {
            "filler": {
                "persistence": False,
                "remote_commands_enabled": True,
                "modes": {"changeover": {"number": 5, "mode_change_states": ["Stopped", "Idle"]}},
                "recipes": RECIPES,
                "initial_recipe": 1,
                "recipe_timeout": 20,
                "equipment_modules": {
                    "robot": {"sim": {**em, "counter": "processed"}},
                    "gripper": {
                        "sim": {
                            **em,
                            "faults": {
                                "wrong_fingers": {"kind": "refuse_recipe", "message": REFUSAL}
                            },
                        }
                    },
                    "vision": {"sim": em},
                },
            }
        },
    }


def write_recipe_cell(tmp_path: Path, cell: str, **unit: Any) -> Path:
    """The cell file in ``tmp_path`` (``unit``: keys replacing the unit's, e.g. persistence)."""
    doc = recipe_cell(cell)
    doc["units"]["filler"].update(unit)
    path = tmp_path / f"{cell}.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path
