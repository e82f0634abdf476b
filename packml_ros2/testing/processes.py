"""Nodes in separate OS processes for tests: started with this interpreter, stopped with SIGINT
(clean shutdown is part of what is tested), killed with SIGKILL (and the shared memory they leave
behind is cleaned up)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from . import shm


class NodeProcess:
    """One child process; its output goes to ``log`` (shown when a test fails)."""

    def __init__(
        self, name: str, args: Sequence[str], log_dir: Path, env: dict[str, str] | None = None
    ):
        self.name = name
        self.args = list(args)
        self.log = log_dir / f"{name}.log"
        self._log_handle = self.log.open("ab")
        child_env = dict(os.environ if env is None else env)
        child_env.setdefault("PYTHONUNBUFFERED", "1")
        # The same interpreter (see the notes: the ROS wheels' bootstrap guard is per venv).
        self.popen = subprocess.Popen(
            [sys.executable, *self.args],
            stdout=self._log_handle,
            stderr=subprocess.STDOUT,
            env=child_env,
            start_new_session=True,
        )

    @property
    def pid(self) -> int:
        return self.popen.pid

    def running(self) -> bool:
        return self.popen.poll() is None

    def stop(self, timeout: float = 10.0) -> int:
        """SIGINT, as Ctrl-C would; returns the exit code (SIGKILL after ``timeout``)."""
        if self.running():
            self.popen.send_signal(signal.SIGINT)
            try:
                return self.popen.wait(timeout)
            except subprocess.TimeoutExpired:
                self.kill()
        return self.popen.returncode

    def kill(self) -> None:
        """SIGKILL, then remove the shared-memory files the process can no longer clean up."""
        if self.running():
            self.popen.kill()
            self.popen.wait(10)
        shm.cleanup()

    def output(self) -> str:
        self._log_handle.flush()
        return self.log.read_text(errors="replace")

    def close(self) -> None:
        if self.running():
            self.stop(5.0)
        self._log_handle.close()


class Processes:
    """The processes a test started; all are stopped at teardown."""

    def __init__(self, log_dir: Path, env: dict[str, str] | None = None):
        self.log_dir = log_dir
        self.env = env
        self.started: list[NodeProcess] = []

    def start(self, name: str, *args: str, env: dict[str, str] | None = None) -> NodeProcess:
        merged = dict(self.env or os.environ)
        merged.update(env or {})
        proc = NodeProcess(name, args, self.log_dir, merged)
        self.started.append(proc)
        return proc

    def module(
        self, name: str, module: str, *args: str, env: dict[str, str] | None = None
    ) -> NodeProcess:
        """``python -m module args...``"""
        return self.start(name, "-m", module, *args, env=env)

    def close(self) -> str:
        """Stop everything; returns the logs of processes that died with an error."""
        failures = []
        for proc in reversed(self.started):
            code = proc.stop(5.0) if proc.running() else proc.popen.returncode
            if code not in (0, None, -signal.SIGKILL, -signal.SIGINT):
                failures.append(f"--- {proc.name} exited {code} ---\n{proc.output()[-3000:]}")
            proc.close()
        return "\n".join(failures)


def wait_until(
    predicate: Callable[[], object],
    timeout: float = 10.0,
    interval: float = 0.01,
    what: str = "condition",
) -> None:
    """Poll ``predicate`` (no fixed sleeps: returns as soon as it holds)."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(interval)


def kill_environ_holders(marker: str) -> list[int]:
    """SIGKILL every process of this user whose environment holds ``marker`` (but this one): what
    a test started, its children and theirs, though a SIGKILLed parent left them orphaned (a node
    the launcher started in a session of its own). Returns their pids."""
    needle, killed = marker.encode(), []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            if needle not in (entry / "environ").read_bytes():
                continue
            os.kill(int(entry.name), signal.SIGKILL)
        except OSError:  # gone meanwhile, or not ours
            continue
        killed.append(int(entry.name))
    return killed
