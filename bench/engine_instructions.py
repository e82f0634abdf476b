"""CPU instructions per engine transition, counted by valgrind (cachegrind): deterministic where
timings on a shared VM vary by 15 %, so a change to the engine's hot path can be judged by a
difference of a few percent. Prints JSON.

    python bench/engine_instructions.py [--cycles 10000]

Runs bench/engine.py's cycles (without EMs, the floor, and with 8 EMs and 32 alarms) under valgrind twice,
for 2,000 and 2,000 + ``cycles`` cycles, and divides the difference of the counts by the extra
transitions: start-up and imports cancel out. Needs valgrind (``apt install valgrind``); about
a minute.
"""

from __future__ import annotations

import argparse
import gc
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
BASE_CYCLES = 2_000
RUNNERS = {
    "packml_ros2": "ours_cycle_runner",
    "floor": "floor_cycle_runner",
    "packml_ros2_8_ems_32_alarms": "ours_with_ems_runner",
}
TRANSITIONS_PER_CYCLE = 6


def count(runner: str, cycles: int) -> int:
    """Instructions valgrind counts for the whole process running ``cycles`` cycles."""
    out = subprocess.run(
        # --trace-children: the interpreter may re-exec itself (the ROS wheels' .pth bootstrap)
        ["valgrind", "--tool=cachegrind", "--cache-sim=no", "--trace-children=yes",
         "--cachegrind-out-file=/dev/null", sys.executable, __file__, "--run", runner, str(cycles)],
        capture_output=True, text=True, check=True,
    ).stderr  # fmt: skip
    refs = re.findall(r"I\s+refs:\s+([\d,]+)", out)
    if not refs:
        raise RuntimeError(f"no instruction count in valgrind's output:\n{out[-2000:]}")
    return int(refs[-1].replace(",", ""))


def run_cycles(runner: str, cycles: int) -> None:
    sys.path.insert(0, str(HERE))
    import engine  # bench/engine.py

    gc.disable()  # as in bench/engine.py
    getattr(engine, runner)()(cycles)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cycles", type=int, default=10_000)
    parser.add_argument("--run", nargs=2, help=argparse.SUPPRESS)  # the child under valgrind
    args = parser.parse_args()
    if args.run:
        run_cycles(args.run[0], int(args.run[1]))
        return 0
    if shutil.which("valgrind") is None:
        print(
            json.dumps({"benchmark": "engine_instructions", "error": "valgrind is not installed"})
        )
        return 1
    result: dict[str, object] = {"benchmark": "engine_instructions", "cycles": args.cycles}
    for name, runner in RUNNERS.items():
        extra = count(runner, BASE_CYCLES + args.cycles) - count(runner, BASE_CYCLES)
        result[name] = {
            "instructions_per_transition": round(extra / (args.cycles * TRANSITIONS_PER_CYCLE))
        }
    ours, floor = (result[name]["instructions_per_transition"] for name in ("packml_ros2", "floor"))  # type: ignore[index]
    result["ratio_packml_ros2_over_floor"] = round(ours / floor, 2)
    json.dump(result, sys.stdout, indent=2)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
