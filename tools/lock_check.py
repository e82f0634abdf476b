"""Compare what ``pip freeze --all`` lists in a venv with requirements/lock.txt.

Run with the venv's python: ``.venv/bin/python tools/lock_check.py`` prints each difference and
exits 1 when there is one (test/test_lock.py runs it). Not compared: what tools/setup.sh builds
here and installs --no-deps from a local file (packml_ros2 editable, packml_interfaces, the ROS 2
command line built from ../shared/vendor): pip freeze shows them as ``-e`` or ``name @ file://``.
Compared besides the lock: requirements/ros-wheels-embedded.lock, the metadata of their ROS
packages that the ros-* wheels carry inside them (``ros-rclpy`` holds an ``rclpy-*.egg-info``), which
pip lists as packages of their own; nothing installs them but their wheel.

``--pip-check`` runs ``pip check`` and prints what it finds, less the local builds'.
``--stale`` prints instead the packages to remove: installed, not local, neither in the lock nor
carried by another installed wheel (tools/setup.sh uninstalls them after an older lock).
"""

from __future__ import annotations

import re
import subprocess
import sys
from importlib import metadata
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
LOCK = ROOT / "requirements" / "lock.txt"
EMBEDDED = ROOT / "requirements" / "ros-wheels-embedded.lock"
_PIN = re.compile(r"^([A-Za-z0-9][A-Za-z0-9._-]*)(?:\[[^\]]*\])?==([^\s;\\]+)", re.MULTILINE)


def canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def pins(text: str) -> dict[str, str]:
    """``name==version`` lines of a requirements or freeze text, by canonical name."""
    return {canonical(m[1]): m[2] for m in _PIN.finditer(text)}


def frozen() -> dict[str, str]:
    """What ``pip freeze --all`` lists in this venv, less the local builds and what they carry
    (the packml_interfaces wheel holds a packml_interfaces egg-info, as the ros-* wheels do)."""
    out = subprocess.run([sys.executable, "-m", "pip", "freeze", "--all"],
                         capture_output=True, text=True, check=True).stdout  # fmt: skip
    local = {canonical(line.split(" @ ")[0]) for line in out.splitlines() if " @ " in line}
    listed = pins("\n".join(line for line in out.splitlines() if " @ " not in line))
    inside = carried(local)  # once: it reads every installed distribution's RECORD
    return {name: v for name, v in listed.items() if name not in inside}


def differences(installed: dict[str, str], locked: dict[str, str]) -> list[str]:
    """One line per package whose installed release is not the locked one."""
    lines = []
    for name in sorted(installed.keys() | locked.keys()):
        have, want = installed.get(name), locked.get(name)
        if have == want:
            continue
        if want is None:
            lines.append(f"{name}=={have} is installed but not in the lock")
        elif have is None:
            lines.append(f"{name}=={want} is locked but not installed")
        else:
            lines.append(f"{name}: {have} installed, {want} locked")
    return lines


def expected() -> dict[str, str]:
    return pins(LOCK.read_text()) | pins(EMBEDDED.read_text())


def carried(owners: set[str] | None = None) -> set[str]:
    """Names whose metadata directory is a file of another installed distribution (of one of
    ``owners`` only, when given)."""
    names = set()
    for dist in metadata.distributions():
        own = canonical(dist.metadata["Name"])
        if owners is not None and own not in owners:
            continue
        for file in dist.files or ():
            top = file.parts[0] if file.parts else ""
            if top.endswith((".egg-info", ".dist-info")) and canonical(top.split("-")[0]) != own:
                names.add(canonical(top.split("-")[0]))
    return names


def pip_check() -> list[str]:
    """``pip check``'s complaints, less those of the local builds (the ROS 2 command line built
    from ../shared/vendor names ROS packages, such as ament_index_python, that exist here only
    inside the ros-* wheels; they are installed --no-deps)."""
    out = subprocess.run([sys.executable, "-m", "pip", "check"],
                         capture_output=True, text=True, check=False).stdout  # fmt: skip
    freeze = subprocess.run([sys.executable, "-m", "pip", "freeze", "--all"],
                            capture_output=True, text=True, check=True).stdout  # fmt: skip
    local = {canonical(line.split(" @ ")[0]) for line in freeze.splitlines() if " @ " in line}
    return [line for line in out.splitlines()
            if line.strip() and not line.startswith("No broken")
            and canonical(line.split()[0]) not in local]  # fmt: skip


def main(argv: list[str]) -> int:
    if argv == ["--pip-check"]:
        complaints = pip_check()
        print("\n".join(complaints))
        return 1 if complaints else 0
    installed = frozen()
    if argv == ["--stale"]:
        keep = pins(LOCK.read_text()).keys() | carried()
        for name in sorted(installed.keys() - keep):
            print(name)
        return 0
    lines = differences(installed, expected())
    for line in lines:
        print(line)
    return 1 if lines else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
