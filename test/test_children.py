"""packml_ros2.children: a child started by spawn() ends when its parent is killed outright."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from packml_ros2 import children

# The child says when it listens, and what ended it.
CHILD = """
import signal, sys, time
from pathlib import Path
out = Path(sys.argv[1])
def stop(signum, _):
    out.write_text(f"stopped by {signal.Signals(signum).name}")
    sys.exit(0)
signal.signal(signal.SIGINT, stop)
out.write_text("ready")
time.sleep(120)
"""

# The parent spawns the child the way the launcher does (plain: as it did before), then waits.
PARENT = """
import subprocess, sys, time
from packml_ros2 import children
argv = [sys.executable, "-c", sys.argv[2], sys.argv[3]]
if sys.argv[1] == "spawn":
    child = children.spawn(argv)
else:
    child = subprocess.Popen(argv, start_new_session=True)
print(child.pid, flush=True)
time.sleep(120)
"""


def _wait_for(path: Path, text: str, timeout: float) -> str:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if path.exists() and path.read_text().startswith(text):
            return path.read_text()
        time.sleep(0.02)
    return path.read_text() if path.exists() else "(nothing)"


@pytest.mark.parametrize("how", ["spawn", "plain"])
def test_a_parent_killed_outright_stops_its_spawned_child(tmp_path: Path, how: str) -> None:
    said = tmp_path / "child.txt"
    parent = subprocess.Popen([sys.executable, "-c", PARENT, how, CHILD, str(said)],
                              stdout=subprocess.PIPE, text=True)  # fmt: skip
    assert parent.stdout is not None
    pid = int(parent.stdout.readline())
    try:
        assert _wait_for(said, "ready", 20) == "ready"
        parent.kill()
        parent.wait()
        if how == "spawn":
            assert _wait_for(said, "stopped", 10) == "stopped by SIGINT"
        else:  # what the launcher did before: the child lives on
            time.sleep(0.5)  # (the absence of a signal: nothing to wait for)
            assert said.read_text() == "ready"
    finally:
        parent.kill()
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)


def test_a_child_spawned_from_another_thread_is_not_tied_to_it() -> None:
    """Linux sends the signal when the forking thread ends: only the main thread asks for it."""
    import threading

    guards: list[object] = []
    thread = threading.Thread(target=lambda: guards.append(children._guard(os.getpid())))
    thread.start()
    thread.join()
    assert guards == [None]
    assert children._guard(os.getpid()) is not None
