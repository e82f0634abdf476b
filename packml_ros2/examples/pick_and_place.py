"""Example EM: a pick-and-place robot with a vacuum gripper, to copy and adapt.

It shows every part of the EM API an integrator needs:

- ``on_resetting``: home the robot (a coroutine; State Complete is reported when it returns);
- ``execute``: the production loop; each pick-and-place is wrapped in ``ctx.finish`` so that a Hold
  or Stop arriving mid-move lets the move end at a safe place before the unit pauses;
- ``on_holding`` / ``on_stopping`` / ``on_aborting``: bring the robot to rest (``on_aborting`` is a
  plain function, as a hardware stop call usually is);
- counting: ``self.count("processed")`` and ``self.count("defective")`` feed the unit's PackTags
  counters; ``self.count("consumed")`` the material used;
- alarms: a lost vacuum raises alarm 201 (the unit's configuration says category 2 -> Stop) and
  clears it when the vacuum is back;
- the robot itself is simulated here (``FakeRobot``); replace it with your driver.

Run it against a unit (e.g. the demo cell's robot_cell):
    pick_and_place --cell demo_cell --unit robot_cell --name robot
"""

from __future__ import annotations

import argparse
import asyncio
import random
import sys
from collections.abc import Sequence

from .. import run
from ..equipment_module import EquipmentModule, StateContext

VACUUM_LOST = 201


class FakeRobot:
    """Stands in for a robot driver: moves take time, the vacuum sometimes fails."""

    def __init__(self, move_time: float = 0.4, seed: int = 1) -> None:
        self.move_time = move_time
        self.random = random.Random(seed)
        self.position = "unknown"
        self.vacuum = False

    async def move_to(self, place: str) -> None:
        await asyncio.sleep(self.move_time)
        self.position = place

    async def grip(self) -> bool:
        await asyncio.sleep(0.05)
        self.vacuum = self.random.random() > 0.01  # 1 % of picks lose the part
        return self.vacuum

    async def release(self) -> None:
        await asyncio.sleep(0.05)
        self.vacuum = False

    def emergency_stop(self) -> None:
        self.vacuum = False


class PickAndPlace(EquipmentModule):
    def __init__(self, name: str, unit: str, cell: str, robot: FakeRobot | None = None) -> None:
        super().__init__(name, unit, cell, lease=1.0)
        self.robot = robot or FakeRobot()

    async def on_resetting(self, ctx: StateContext) -> None:
        await self.robot.move_to("home")

    async def on_starting(self, ctx: StateContext) -> None:
        await self.robot.release()

    async def execute(self, ctx: StateContext) -> None:
        while True:  # runs until the unit leaves Execute (a continuous production run)
            await ctx.finish(self.pick_and_place())

    async def pick_and_place(self) -> None:
        """One cycle. Wrapped in ctx.finish by execute(): never interrupted halfway."""
        await self.robot.move_to("pick")
        if not await self.robot.grip():
            self.raise_alarm(VACUUM_LOST, message="vacuum lost at pick")
            await self.robot.release()
            self.clear_alarm(VACUUM_LOST)
            self.count("defective")
            return
        self.count("consumed")
        await self.robot.move_to("place")
        await self.robot.release()
        self.count("processed")

    async def on_holding(self, ctx: StateContext) -> None:
        await self.robot.move_to("home")  # the running cycle has already finished

    async def on_stopping(self, ctx: StateContext) -> None:
        await self.robot.release()
        await self.robot.move_to("home")

    def on_aborting(self, ctx: StateContext) -> None:
        self.robot.emergency_stop()  # plain function: runs in a worker thread


def main(argv: Sequence[str] | None = None) -> int:
    args = run.init(argv)
    parser = argparse.ArgumentParser(description="Example pick-and-place EM")
    parser.add_argument("--cell", default="demo_cell")
    parser.add_argument("--unit", default="robot_cell")
    parser.add_argument("--name", default="robot")
    opts = parser.parse_args(args)
    node = PickAndPlace(opts.name, opts.unit, opts.cell)
    return run.spin([node], on_shutdown=node.close)


if __name__ == "__main__":
    sys.exit(main())
