"""package.xml declares what the code imports, so that ``rosdep install --from-paths src`` in a ROS 2
workspace brings everything: every third-party import of the package (packml_ros2/, launch/)
has an exec_depend (or depend), every import of the tests (test/, packml_ros2/testing/) a
test_depend or exec_depend; ROS packages by their name, Python modules by their rosdep key; a
module without a key has a documented pip route. And no key is declared that nothing imports."""

from __future__ import annotations

import ast
import sys
from collections.abc import Iterable
from pathlib import Path

from catkin_pkg.package import parse_package

ROOT = Path(__file__).resolve().parents[1]
#: Python modules -> their rosdep keys (rosdistro's rosdep/python.yaml).
ROSDEP = {
    "yaml": "python3-yaml",
    "rosbags": "python3-rosbags-pip",
    "lz4": "python3-lz4",  # rosbags brings it; the bag reader bounds its decompression
    "fastapi": "python3-fastapi",
    "uvicorn": "python3-uvicorn",
    "starlette": "python3-fastapi",  # FastAPI's own foundation, installed with it
    "cryptography": "python3-cryptography",
    "pytest": "python3-pytest",
    "hypothesis": "python3-hypothesis",
    "httpx": "python3-httpx",
    "catkin_pkg": "python3-catkin-pkg",
    "paho": "python3-paho-mqtt",
}
#: Modules without a rosdep key: installed with pip (setup.py's install_requires; the README's
#: workspace section says so).
PIP_ONLY = {"asyncua": "asyncua", "pysparkplug": "pysparkplug"}  # (the second: tests only)
LOCAL = {"packml_ros2", "test"}


def imports(paths: Iterable[Path]) -> dict[str, set[str]]:
    """Top-level third-party modules imported by ``paths``: {module: {file, ...}}."""
    found: dict[str, set[str]] = {}
    for path in paths:
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                top = name.split(".")[0]
                if top not in sys.stdlib_module_names and top not in LOCAL:
                    found.setdefault(top, set()).add(str(path.relative_to(ROOT)))
    return found


def python_files(*dirs: str, exclude: str = "") -> list[Path]:
    return [
        p
        for d in dirs
        for p in sorted((ROOT / d).rglob("*.py"))
        if "node_modules" not in p.parts and not (exclude and exclude in p.parts)
    ]


def keys(declared: list[object]) -> set[str]:
    return {d.name for d in declared}  # type: ignore[attr-defined]


def missing(modules: dict[str, set[str]], declared: set[str]) -> list[str]:
    out = []
    for module, where in sorted(modules.items()):
        if module in PIP_ONLY:
            continue
        key = ROSDEP.get(module, module)  # a ROS package's key is its name
        if key not in declared:
            out.append(
                f"{module} (imported by {', '.join(sorted(where))}): no {key} in package.xml"
            )
    return out


def test_every_import_has_its_rosdep_key_and_every_key_an_import() -> None:
    package = parse_package(str(ROOT / "package.xml"))
    runtime = keys(package.exec_depends) | keys(package.build_export_depends)
    tests = runtime | keys(package.test_depends)
    shipped = imports(python_files("packml_ros2", "launch", exclude="testing"))
    tested = imports(python_files("test") + python_files("packml_ros2/testing"))
    problems = missing(shipped, runtime) + missing(tested, tests)
    assert not problems, "\n".join(problems)
    used = {ROSDEP.get(m, m) for m in {*shipped, *tested}}
    unused = sorted((runtime | tests) - used)
    assert not unused, f"package.xml declares keys nothing imports: {unused}"


def test_modules_without_a_rosdep_key_have_a_documented_pip_route() -> None:
    setup = (ROOT / "setup.py").read_text(encoding="utf-8")
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    for pip_name in PIP_ONLY.values():
        assert f'"{pip_name}' in setup, f"{pip_name} is not in setup.py's install_requires"
        assert f"pip install {pip_name}" in readme, (
            f"the README does not say: pip install {pip_name}"
        )
