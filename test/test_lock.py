"""Issue 24: requirements/lock.txt pins the whole closure that tools/setup.sh installs, hashed, and
the venv holds exactly it. A fresh clone took PyYAML 6.0.4 (released since) when only the direct
requirements were pinned; 141 of 180 packages were pinned nowhere."""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
_spec = importlib.util.spec_from_file_location("lock_check", REPO / "tools" / "lock_check.py")
assert _spec is not None and _spec.loader is not None
lock_check = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(lock_check)


def test_pip_freeze_is_the_lock() -> None:
    """``pip freeze --all`` of this venv against the lock (and what the ros-* wheels carry), less
    what setup.sh builds here: packml_ros2, packml_interfaces, the vendored ROS 2 command line."""
    result = subprocess.run([sys.executable, str(REPO / "tools" / "lock_check.py")],
                            capture_output=True, text=True, timeout=100, check=False)  # fmt: skip
    assert result.returncode == 0, (
        "pip freeze --all differs from requirements/lock.txt (run tools/setup.sh; after changing "
        f"requirements/*.txt or setup.py, tools/lock.sh):\n{result.stdout}{result.stderr}"
    )


def test_a_difference_is_named() -> None:
    installed = {"pyyaml": "6.0.4", "pip": "26.3", "stray": "1.0"}
    locked = {"pyyaml": "6.0.3", "pip": "26.3", "setuptools": "79.0.1"}
    assert lock_check.differences(installed, locked) == [
        "pyyaml: 6.0.4 installed, 6.0.3 locked",
        "setuptools==79.0.1 is locked but not installed",
        "stray==1.0 is installed but not in the lock",
    ]
    freeze = (
        "PyYAML==6.0.4\n-e git+x#egg=packml_ros2\npackml_interfaces @ file:///x.whl\nros_rclpy==9\n"
    )
    assert lock_check.pins(freeze) == {"pyyaml": "6.0.4", "ros-rclpy": "9"}


def test_the_lock_holds_every_direct_pin_pip_and_setuptools_each_hashed() -> None:
    text = lock_check.LOCK.read_text()
    locked = lock_check.pins(text)
    for inputs in sorted((REPO / "requirements").glob("*.txt")):
        if inputs != lock_check.LOCK:
            for name, version in lock_check.pins(inputs.read_text()).items():
                assert locked.get(name) == version, (inputs.name, name, version, locked.get(name))
    assert {"pip", "setuptools", "pyyaml"} <= locked.keys()
    entries = re.split(r"\n(?=\S)", text.split("\n", 2)[2].strip())  # after the two header lines
    assert len(entries) == len(locked)
    assert all("--hash=sha256:" in entry for entry in entries), [
        e.split()[0] for e in entries if "--hash" not in e]  # fmt: skip
    # every install path installs the lock, hashes required; nothing else from an index
    setup = (REPO / "tools" / "setup.sh").read_text()
    assert "install --require-hashes --no-deps -r requirements/lock.txt" in setup
    assert "--upgrade" not in setup and "install -r " not in setup
