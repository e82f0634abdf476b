"""Make a virtual environment with packml_ros2 installed editable a working ament prefix, as colcon's
install space is one, so that ``ros2 run packml_ros2 <executable>`` and ``ros2 launch packml_ros2
cell.launch.py`` find the package there:

- ``<venv>/lib/packml_ros2/<executable>``: every console script of setup.py (where setup.cfg puts
  them for colcon), linked to the venv's own ``bin/<executable>``;
- ``<venv>/share/...``: setup.py's ``data_files`` (the ament index marker, package.xml, launch/,
  config/), linked to the files of this checkout, so an edit is seen at once, like the code;
- ``<site-packages>/packml_ros2_ament_prefix.pth``: every Python of the venv has the venv in
  ``AMENT_PREFIX_PATH`` (appended when the variable names other prefixes, e.g. a workspace).

pip's editable install does none of this (it installs neither data_files nor scripts elsewhere
than bin/). tools/setup.sh runs this after it; it is idempotent. Usage:
``python tools/ament_prefix.py [VENV]`` (default: the running interpreter's prefix).
"""

from __future__ import annotations

import os
import runpy
import sys
import sysconfig
from pathlib import Path
from typing import Any

import setuptools

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "packml_ros2"
PTH = f"{PACKAGE}_ament_prefix.pth"
# One line, run by site.py at every start of the venv's Python (see the module docstring).
PTH_LINE = (
    "import os, sys; p = os.environ.get('AMENT_PREFIX_PATH', ''); "
    "os.environ['AMENT_PREFIX_PATH'] = p if sys.prefix in p.split(os.pathsep) "
    "else os.pathsep.join(filter(None, (p, sys.prefix)))\n"
)


def setup_arguments() -> dict[str, Any]:
    """The keyword arguments setup.py passes to ``setuptools.setup`` (setup.py is the one place
    that lists the data files and executables)."""
    captured: dict[str, Any] = {}
    real = setuptools.setup
    setuptools.setup = lambda **kwargs: captured.update(kwargs)  # type: ignore[assignment]
    cwd = os.getcwd()
    try:
        os.chdir(ROOT)  # setup.py globs relative paths
        runpy.run_path(str(ROOT / "setup.py"), run_name="__main__")
    finally:
        os.chdir(cwd)
        setuptools.setup = real
    return captured


def link(target: Path, link_path: Path) -> None:
    link_path.parent.mkdir(parents=True, exist_ok=True)
    if link_path.is_symlink() or link_path.exists():
        if link_path.is_symlink() and Path(os.readlink(link_path)) == target:
            return
        link_path.unlink()
    link_path.symlink_to(target)


def install(venv: Path) -> list[Path]:
    """Create the links and the .pth file in ``venv``; returns what it made."""
    args = setup_arguments()
    made: list[Path] = []
    for destination, files in args["data_files"]:
        for name in files:
            made.append(venv / destination / Path(name).name)
            link(ROOT / name, made[-1])
    scripts = [spec.split("=", 1)[0].strip() for spec in args["entry_points"]["console_scripts"]]
    for script in scripts:
        made.append(venv / "lib" / PACKAGE / script)
        link(venv / "bin" / script, made[-1])
    purelib = Path(sysconfig.get_paths(vars={"base": str(venv), "platbase": str(venv)})["purelib"])
    made.append(purelib / PTH)
    made[-1].write_text(PTH_LINE, encoding="utf-8")
    return made


def main(argv: list[str]) -> int:
    venv = Path(argv[1] if len(argv) > 1 else sys.prefix).resolve()
    made = install(venv)
    print(f"{venv}: ament prefix of {PACKAGE} ({len(made)} entries)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
