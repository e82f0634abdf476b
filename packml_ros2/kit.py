"""The EM kit: a new ament_python package with an equipment module, its entry point, a cell-file
snippet and a pytest test that drives it through its states against a real unit
(:mod:`packml_ros2.testing.em_harness`). ``packml new em <name>`` writes it; it builds with colcon
and its test passes with ``colcon test``."""

from __future__ import annotations

import re
from pathlib import Path

NAME = re.compile(r"^[a-z][a-z0-9_]{0,62}$")


def camel(name: str) -> str:
    return "".join(part.capitalize() for part in name.split("_") if part) or "Em"


def name_problem(name: str) -> str | None:
    """Why ``name`` cannot name an EM package (a ROS package name that is a Python module too)."""
    if not NAME.match(name) or "__" in name or name.endswith("_"):
        return (
            f"{name!r} is not a package name: lower-case letters, digits and single "
            "underscores, starting with a letter (e.g. gripper, vacuum_gripper)"
        )
    return None


def files(name: str) -> dict[str, str]:
    """The package's files, path -> text."""
    cls = camel(name)
    return {
        "package.xml": PACKAGE_XML.format(name=name),
        "setup.py": SETUP_PY.format(name=name),
        "setup.cfg": SETUP_CFG.format(name=name),
        f"resource/{name}": "",
        f"{name}/__init__.py": f'"""The {name} equipment module."""\n',
        f"{name}/em.py": EM_PY.format(name=name, cls=cls),
        "cell.yaml": CELL_YAML.format(name=name, cls=cls),
        f"test/test_{name}.py": TEST_PY.format(name=name, cls=cls),
        "README.md": README_MD.format(name=name, cls=cls),
    }


def create(name: str, parent: Path) -> Path:
    """Write the package ``name`` into ``parent``; ValueError with a sentence when it cannot."""
    problem = name_problem(name)
    if problem is not None:
        raise ValueError(problem)
    root = parent / name
    if root.exists():
        raise ValueError(f"{root} exists already: choose another name or directory")
    for path, text in files(name).items():
        target = root / path
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text(text, encoding="utf-8")
    return root


PACKAGE_XML = """\
<?xml version="1.0"?>
<?xml-model href="http://download.ros.org/schema/package_format3.xsd" schematypens="http://www.w3.org/2001/XMLSchema"?>
<package format="3">
  <name>{name}</name>
  <version>0.1.0</version>
  <description>The {name} equipment module of a PackML unit (packml_ros2).</description>
  <maintainer email="you@example.com">you</maintainer>
  <license>Apache-2.0</license>

  <exec_depend>packml_ros2</exec_depend>
  <exec_depend>rclpy</exec_depend>
  <test_depend>python3-pytest</test_depend>

  <export>
    <build_type>ament_python</build_type>
  </export>
</package>
"""

SETUP_PY = """\
from setuptools import find_packages, setup

setup(
    name="{name}",
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/{name}"]),
        ("share/{name}", ["package.xml", "cell.yaml"]),
    ],
    install_requires=["setuptools"],
    extras_require={{"test": ["pytest"]}},  # colcon test runs pytest
    zip_safe=True,
    entry_points={{"console_scripts": ["{name} = {name}.em:main"]}},
)
"""

SETUP_CFG = """\
[develop]
script_dir=$base/lib/{name}
[install]
install_scripts=$base/lib/{name}
"""

EM_PY = '''\
"""The {name} equipment module: follows its unit's state and reports State Complete.

Run: ``{name} <unit> [<cell>]`` (or ``ros2 run {name} {name} <unit> <cell>``).
"""

from __future__ import annotations

import asyncio
import sys
from collections.abc import Sequence

from packml_ros2 import run
from packml_ros2.equipment_module import EquipmentModule, StateContext


class {cls}(EquipmentModule):
    """Replace the sleeps with your hardware's calls. Every hook is optional: a state without
    one is reported complete at once."""

    #: s one production cycle takes
    cycle_time = 0.2

    async def on_resetting(self, ctx: StateContext) -> None:
        await asyncio.sleep(0.05)  # home the axes, check the air pressure...

    async def on_starting(self, ctx: StateContext) -> None:
        await asyncio.sleep(0.05)

    async def execute(self, ctx: StateContext) -> None:
        """Production: one product per cycle. Hold or Stop in the middle of a cycle lets the
        cycle finish first (``ctx.finish``)."""
        while True:
            await ctx.finish(asyncio.sleep(self.cycle_time))
            self.count("processed")

    async def on_stopping(self, ctx: StateContext) -> None:
        await asyncio.sleep(0.05)  # park


def main(argv: Sequence[str] | None = None) -> int:
    args = run.init(argv)
    if not args:
        print(__doc__)
        return 2
    unit, cell = args[0], (args[1] if len(args) > 1 else "")
    node = {cls}("{name}", unit, cell)
    return run.spin([node], on_shutdown=node.close)


if __name__ == "__main__":
    sys.exit(main())
'''

CELL_YAML = """\
# A cell-file snippet: the unit that owns this EM lists it under equipment_modules.
# Start the EM beside the unit: `{name} <unit> <cell>` (or `ros2 run {name} {name} <unit> <cell>`);
# a launcher that starts real EMs takes `run: {name}.em:{cls}`.
cell: my_cell
units:
  my_unit:
    em_lease: 2.0
    equipment_modules:
      {name}:
        lost_reaction: stop
"""

TEST_PY = '''\
"""{cls} against a real unit in this process (packml_ros2.testing.em_harness): State Complete
in every state, counts."""

from __future__ import annotations

from {name}.em import {cls}
from packml_ros2.testing.em_harness import EmTestUnit


def test_{name}_goes_through_every_state(ros, tmp_path) -> None:
    unit = EmTestUnit(ros, tmp_path, {{"{name}": {{}}}})
    ros.add({cls}("{name}", unit.unit, unit.cell, context=ros.context))
    unit.check_lifecycle("{name}")


def test_{name}_counts_what_it_produces(ros, tmp_path) -> None:
    unit = EmTestUnit(ros, tmp_path, {{"{name}": {{}}}})
    ros.add({cls}("{name}", unit.unit, unit.cell, context=ros.context))
    unit.wait_online("{name}")
    unit.to_execute()
    unit.wait_count("processed", 2)
'''

README_MD = """\
# {name}

A PackML equipment module (packml_ros2). `{name}/em.py` is the EM ({cls}), `cell.yaml` a
cell-file snippet, `test/test_{name}.py` its test against a real unit.

```sh
cd ~/ws && colcon build --packages-select {name}
colcon test --packages-select {name} && colcon test-result --verbose
```
"""
