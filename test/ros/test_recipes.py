"""Issue 32, done when: a changeover across a unit with three EMs, one of which refuses once,
runs from the CLI (the HMI's and OPC UA's: test/hmi/test_recipe_browser.py,
test/opcua/test_opcua_recipes.py); a recipe change during Execute is refused with its reason; the
line report shows changeover time as its own bucket; all of it survives a restart and replays
from a bag.

The EMs are the integrator's own code (``run: my_ems:Class``, an ``on_recipe`` hook each), started
by ``packml launch`` as the README says; the vision EM refuses the first recipe 2 it is sent."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import yaml

from .test_own_ems import LaunchedHere, env_for, packml

pytestmark = pytest.mark.ros

EMS = textwrap.dedent(
    """
    import asyncio, os
    from packml_ros2.equipment_module import EquipmentModule, RecipeRefused

    def trace(line: str) -> None:
        with open(os.environ["EMS_TRACE"], "a") as f:
            f.write(line + "\\n")

    class Robot(EquipmentModule):
        async def execute(self, ctx):  # produces until commanded
            while True:
                await ctx.finish(asyncio.sleep(0.2))
                self.count("processed")

        async def on_recipe(self, recipe):
            await asyncio.sleep(0.2)  # the robot changes its program
            trace(f"{self.em_name} applied {recipe.id} valves={recipe.parameter('valves')}")

    class Gripper(EquipmentModule):
        def on_recipe(self, recipe):  # a plain function: runs in a thread
            trace(f"{self.em_name} applied {recipe.id} label={recipe.parameter('label')}")

    class Vision(EquipmentModule):
        refused = False

        async def on_recipe(self, recipe):
            if recipe.id == 2 and not Vision.refused:
                Vision.refused = True
                trace(f"{self.em_name} refused {recipe.id}")
                raise RecipeRefused("no inspection program for 1.0 l bottles yet")
            trace(f"{self.em_name} applied {recipe.id}")
    """
)
RECIPES = [
    {
        "id": 1,
        "name": "cola 0.5",
        "unit": "bottles",
        "primary_qty": 1200,
        "process_variables": [
            {"id": 1, "name": "label", "type": "string", "value": "COLA"},
            {"id": 2, "name": "valves", "type": "dint", "value": 12},
        ],
    },
    {
        "id": 2,
        "name": "water 1.0",
        "unit": "bottles",
        "primary_qty": 800,
        "process_variables": [
            {"id": 1, "name": "label", "type": "string", "value": "AQUA"},
            {"id": 2, "name": "valves", "type": "dint", "value": 8},
        ],
    },
]


def write_cell(tmp_path: Path, cell: str) -> Path:
    (tmp_path / "my_ems.py").write_text(EMS)
    doc = {
        "cell": cell,
        "units": {
            "filler": {
                "persistence": {"path": str(tmp_path / "filler.sqlite3")},
                "remote_commands_enabled": True,
                "modes": {"changeover": {"number": 5, "mode_change_states": ["Stopped", "Idle"]}},
                "recipes": RECIPES,
                "initial_recipe": 1,
                "recipe_timeout": 20,
                "equipment_modules": {
                    "robot": {"run": "my_ems:Robot"},
                    "gripper": {"run": "my_ems:Gripper"},
                    "vision": {"run": "my_ems:Vision"},
                },
            }
        },
    }
    path = tmp_path / f"{cell}.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def trace(tmp_path: Path) -> list[str]:
    path = tmp_path / "trace.txt"
    return path.read_text().splitlines() if path.exists() else []


def test_a_changeover_from_the_cli_with_real_ems_survives_a_restart_and_replays(
    tmp_path: Path,
) -> None:
    cell = "recipes32"
    path = write_cell(tmp_path, cell)
    launch = LaunchedHere([str(path)], tmp_path)
    recorder = None
    try:
        launch.wait_ready(90)
        bag = tmp_path / "shift_1"
        recorder = subprocess.Popen(
            [sys.executable, "-m", "packml_ros2.cli.main", "record", cell, "-o", str(bag)],
            stdout=(tmp_path / "record.log").open("wb"),
            stderr=subprocess.STDOUT,
            env=env_for(tmp_path),
        )
        listed = packml(tmp_path, "recipe", "filler", "--cell", cell, "--timeout", "30")
        assert listed.returncode == 0, listed.stderr
        assert "*    1  cola 0.5" in listed.stdout and "     2  water 1.0" in listed.stdout

        shown = packml(tmp_path, "recipe", "filler", "--show", "2", "--timeout", "30")
        assert shown.returncode == 0, shown.stderr
        assert any(
            line.startswith("* valves") and "12" in line and "8" in line
            for line in shown.stdout.splitlines()
        ), shown.stdout

        # 1. the vision EM refuses once: every EM is rolled back, the unit stays on recipe 1
        first = packml(tmp_path, "recipe", "filler", "2", "--timeout", "30")
        assert first.returncode == 1, first.stdout + first.stderr
        assert "vision: refused: no inspection program for 1.0 l bottles yet" in first.stdout
        assert "rolled back to 1 'cola 0.5'" in first.stdout
        lines = trace(tmp_path)
        assert "vision refused 2" in lines
        assert "robot applied 2 valves=8" in lines and "robot applied 1 valves=12" in lines
        # 2. again: applied by all three
        second = packml(tmp_path, "recipe", "filler", "water 1.0", "--timeout", "30")
        assert second.returncode == 0, second.stdout + second.stderr
        assert "recipe 2 'water 1.0' applied" in second.stdout
        assert {"vision applied 2", "gripper applied 2 label=AQUA"} <= set(trace(tmp_path))
        # 3. in Execute: refused with its reason, nothing sent to the EMs
        for verb in ("reset", "start"):
            assert packml(tmp_path, "cmd", "filler", verb, "--timeout", "30").returncode == 0
        sent = len(trace(tmp_path))
        refused = packml(tmp_path, "recipe", "filler", "1", "--timeout", "30")
        assert refused.returncode == 1
        assert "refused in EXECUTE" in refused.stdout and "only in STOPPED, IDLE, COMPLETE" in (
            refused.stdout
        )
        assert len(trace(tmp_path)) == sent
        assert packml(tmp_path, "cmd", "filler", "stop", "--timeout", "30").returncode == 0
        # 4. the changeover mode: its own planned bucket in the line report
        assert packml(tmp_path, "mode", "filler", "changeover", "--timeout", "30").returncode == 0
        assert packml(tmp_path, "mode", "filler", "production", "--timeout", "30").returncode == 0
        report = packml(
            tmp_path, "report", cell, "--window", "lifetime", "--format", "json", "--timeout", "30"
        )
        assert report.returncode == 0, report.stderr
        assert '"changeover"' in report.stdout, report.stdout[:2000]
        table = packml(tmp_path, "report", cell, "--window", "lifetime", "--timeout", "30")
        assert "CHANGEOVER" in table.stdout, table.stdout
    finally:
        if recorder is not None:
            recorder.send_signal(signal.SIGINT)
            recorder.wait(30)
        assert launch.ctrl_c(60) == 0, launch.output()[-3000:]

    # 5. the bag replays: the changeovers, the refusal and the rollback included
    replayed = packml(tmp_path, "replay", str(tmp_path / "shift_1"), timeout=300)
    assert replayed.returncode == 0, replayed.stdout + replayed.stderr
    # 6. after a restart the unit is on recipe 2 (persisted), its EMs asked nothing meanwhile
    done = len(trace(tmp_path))
    again = LaunchedHere([str(path)], tmp_path)
    try:
        again.wait_ready(90)
        listed = packml(tmp_path, "recipe", "filler", "--timeout", "30")
        assert "*    2  water 1.0" in listed.stdout, listed.stdout
        assert len(trace(tmp_path)) == done
    finally:
        assert again.ctrl_c(60) == 0
