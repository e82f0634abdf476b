"""Issue 26 item 4: the EM kit. ``packml new em <name>`` writes an ament_python package whose test
(the EM driven through its states by packml_ros2.testing.em_harness against a real unit) passes,
run by pytest in place and, in a colcon workspace with the venv as underlay, by ``colcon build``
and ``colcon test``."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from packml_ros2.kit import files

from .tools import environment, packml, require, shell


def test_packml_new_em_writes_the_package(tmp_path: Path) -> None:
    made = packml("new", "em", "vacuum_gripper", "--dir", str(tmp_path), home=tmp_path)
    assert made.returncode == 0, made.stderr
    root = tmp_path / "vacuum_gripper"
    assert sorted(str(p.relative_to(root)) for p in root.rglob("*") if p.is_file()) == sorted(
        files("vacuum_gripper")
    )
    assert "class VacuumGripper(EquipmentModule)" in (root / "vacuum_gripper/em.py").read_text()
    assert "vacuum_gripper = vacuum_gripper.em:main" in (root / "setup.py").read_text()
    again = packml("new", "em", "vacuum_gripper", "--dir", str(tmp_path), home=tmp_path)
    assert again.returncode == 2 and "exists already" in again.stderr


@pytest.mark.parametrize("name", ["Gripper", "1arm", "my-arm", "a__b", "arm_", ""])
def test_a_name_that_is_no_package_name_is_refused(tmp_path: Path, name: str) -> None:
    made = packml("new", "em", name, "--dir", str(tmp_path), home=tmp_path)
    assert made.returncode == 2 and "not a package name" in made.stderr, made.stderr
    assert not any(tmp_path.iterdir()) or not (tmp_path / name).exists()


@pytest.mark.ros
def test_the_generated_test_passes_in_place(tmp_path: Path) -> None:
    made = packml("new", "em", "gripper", "--dir", str(tmp_path), home=tmp_path)
    assert made.returncode == 0, made.stderr
    root = tmp_path / "gripper"
    path = [str(root), *filter(None, [os.environ.get("PYTHONPATH")])]
    env = dict(environment(tmp_path), PYTHONPATH=os.pathsep.join(path))
    result = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:randomly", "test"],
                            cwd=root, env=env, capture_output=True, text=True, timeout=300,
                            check=False)  # fmt: skip
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]
    assert "2 passed" in result.stdout


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_the_generated_package_builds_with_colcon_and_its_test_passes(tmp_path: Path) -> None:
    require("colcon")
    script = (
        "mkdir -p ws/src && cd ws/src && packml new em gripper\n"
        "cd .. && colcon build\n"
        "colcon test --packages-select gripper\n"
        "colcon test-result --verbose\n"
        "ls install/gripper/lib/gripper/gripper\n"
    )
    built = shell(script, tmp_path, tmp_path, timeout=900)
    assert built.returncode == 0, built.stdout[-4000:]
    assert "Summary: 1 package finished" in built.stdout, built.stdout[-4000:]
    assert "2 tests, 0 errors, 0 failures, 0 skipped" in built.stdout, built.stdout[-4000:]
