"""What the tests of the real ROS 2 tools share: where the venv's ``ros2`` and ``colcon`` are (and a
skip with the reason where the vendored sources are missing), the README's code blocks, shells
that run README lines verbatim, and a cell started the way a user starts it."""

from __future__ import annotations

import os
import re
import shlex
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
VENV_BIN = Path(sys.executable).parent  # the venv this test runs in (tools/setup.sh --test)
VENDOR = ROOT.parent / "shared" / "vendor" / "ros2-tools"
PACKML = [sys.executable, "-m", "packml_ros2.cli.main"]


def require(*tools: str) -> None:
    """Skip (vendored sources missing: a user's machine) or fail (sources there, tools not
    installed: tools/setup.sh --test did not do its job) unless ``tools`` are in the venv."""
    missing = [t for t in tools if not (VENV_BIN / t).exists()]
    if not missing:
        return
    if not VENDOR.is_dir():
        pytest.skip(
            f"{', '.join(missing)} not installed: tools/setup.sh --test builds them from "
            "../shared/vendor/ros2-tools, which this checkout does not have beside it"
        )
    pytest.fail(
        f"{', '.join(missing)} missing in {VENV_BIN} although {VENDOR} exists: run tools/setup.sh --test"
    )


# -- the README ------------------------------------------------------------------------------------------
def code_blocks(language: str) -> list[str]:
    """The README's fenced code blocks of ``language`` (```sh, ```console ...), in order."""
    text = README.read_text(encoding="utf-8")
    return re.findall(rf"^```{language}\n(.*?)^```", text, flags=re.MULTILINE | re.DOTALL)


def console_commands(block: str) -> list[tuple[str, list[str]]]:
    """``$ command`` lines of a console block with the output shown under each."""
    out: list[tuple[str, list[str]]] = []
    for line in block.splitlines():
        if line.startswith("$ "):
            out.append((line[2:], []))
        elif out:
            out[-1][1].append(line)
    return out


def shown_in(expected: list[str], actual: str) -> str | None:
    """None if the README's ``expected`` output is in ``actual``: its lines in order, ``...`` for
    lines left out, blank lines at the end ignored; else the first line not found."""
    lines = [line.rstrip() for line in actual.splitlines()]
    i = 0
    for want in [e.rstrip() for e in expected]:
        if want in ("", "..."):
            continue
        while i < len(lines) and lines[i] != want:
            i += 1
        if i == len(lines):
            return want
        i += 1
    return None


# -- shells -------------------------------------------------------------------------------------------------
def environment(home: Path) -> dict[str, str]:
    """The test's environment (its ROS domain, localhost only) with ``home`` as HOME: admin data,
    ~/ws and ROS logs stay in the test's directory."""
    return dict(os.environ, HOME=str(home), PYTHONUNBUFFERED="1")


def shell(
    script: str, home: Path, cwd: Path, timeout: float = 120
) -> subprocess.CompletedProcess[str]:
    """``script`` in bash with the venv active (the underlay), stopping at the first failure;
    ``stdout`` holds what a terminal would show (stderr interleaved). On a timeout (or the test's)
    every process it started is killed, builds included."""
    proc = subprocess.Popen(
        ["bash", "-c", f"set -eo pipefail\n. {shlex.quote(str(VENV_BIN / 'activate'))}\n{script}"],
        cwd=cwd, env=environment(home), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
        text=True, start_new_session=True,
    )  # fmt: skip
    try:
        out, _ = proc.communicate(timeout=timeout)
    except BaseException:
        with suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        raise
    return subprocess.CompletedProcess(proc.args, proc.returncode, out)


class Background:
    """A command line in bash (venv active), in a session of its own: ``ctrl_c`` sends SIGINT to
    every process of it at once, as a terminal does."""

    def __init__(self, script: str, home: Path, cwd: Path, log: Path) -> None:
        self.log = log
        self._out = log.open("wb")
        self.proc = subprocess.Popen(
            ["bash", "-c", f". {shlex.quote(str(VENV_BIN / 'activate'))}\n{script}"],
            cwd=cwd, env=environment(home), stdout=self._out, stderr=subprocess.STDOUT,
            start_new_session=True,
        )  # fmt: skip
        self.marked = 0

    def output(self) -> str:
        return self.log.read_text(errors="replace")

    def wait_for(self, text: str, timeout: float = 60.0) -> None:
        deadline = time.monotonic() + timeout
        while text not in self.output():
            if self.proc.poll() is not None or time.monotonic() > deadline:
                raise AssertionError(
                    f"{text!r} not seen (exit {self.proc.poll()}):\n{self.output()}"
                )
            time.sleep(0.05)

    def ctrl_c(self, timeout: float = 30.0) -> int:
        self.marked = len(self.output())
        os.killpg(self.proc.pid, signal.SIGINT)
        try:
            return self.proc.wait(timeout)
        finally:
            self._out.close()

    def after_ctrl_c(self) -> str:
        return self.output()[self.marked :]

    def kill(self) -> None:
        """Whatever of the session is left (the processes of a failed test)."""
        with suppress(ProcessLookupError):
            os.killpg(self.proc.pid, signal.SIGKILL)
        self.proc.wait()
        self._out.close()


def packml(*args: str, home: Path, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*PACKML, *args], env=environment(home), capture_output=True, text=True,
                          timeout=timeout, check=False)  # fmt: skip


def wait_all_ems_online(home: Path, timeout: float = 60.0) -> str:
    """``packml status`` until both demo units list every EM online (robot_cell 5/5, case_packer
    2/2): the cell answers and a reset will not be refused for a missing EM."""
    deadline = time.monotonic() + timeout
    while True:
        status = packml("status", "--cell", "demo_cell", home=home)
        if re.search(r"case_packer .* 2/2 ", status.stdout) and re.search(
            r"robot_cell .* 5/5 ", status.stdout
        ):
            return status.stdout
        if time.monotonic() > deadline:
            raise AssertionError(f"the demo cell is not up:\n{status.stdout}{status.stderr}")


@contextmanager
def ros2_daemon(home: Path) -> Iterator[None]:
    """The ros2 daemon of this test's domain (port 11511 + ROS_DOMAIN_ID), stopped at the end."""
    try:
        yield
    finally:
        shell("ros2 daemon stop >/dev/null 2>&1 || true", home, ROOT, timeout=30)
