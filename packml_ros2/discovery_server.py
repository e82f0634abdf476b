"""A Fast DDS Discovery Server hosted by ``packml launch`` (the cell file's
``discovery: {server: host:port, host_server: true}``, core/discovery.py).

The server is Fast DDS's own tool, ``fastdds discovery -l <address> -p <port>``: from a ROS 2
install (``fastdds`` on the PATH), or from the ``ros-fastdds`` wheel this project's venv installs
(``<venv>/tools/fastdds/fastdds.py``; its binary finds its libraries only with the wheel's library
directories on ``LD_LIBRARY_PATH``, which is set for it alone). It runs as a child process in a
session of its own (Ctrl-C reaches the launcher, which stops it after the cell's nodes).
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import signal
import subprocess
import sys
import sysconfig
import tempfile
import time
from pathlib import Path

from .children import spawn

#: Seconds the server has to say it runs.
START_TIMEOUT = 15.0
STARTED = b"Server started"


class DiscoveryServerError(RuntimeError):
    """The server could not be started (no tool, the address not on this host, the port taken)."""


def server_command(host: str, port: int) -> tuple[list[str], dict[str, str]]:
    """argv and the environment of the Fast DDS discovery tool serving ``host``:``port``."""
    args = ["discovery", "-l", host, "-p", str(port)]
    tool = Path(sys.prefix) / "tools" / "fastdds" / "fastdds.py"
    if tool.is_file():  # the ros-fastdds wheel's tool (its .venv/bin/fastdds lacks the libraries)
        site = Path(sysconfig.get_paths()["purelib"])
        libs = [str(Path(sys.prefix) / "lib"), str(site / "ros_fastdds.libs")]
        old = os.environ.get("LD_LIBRARY_PATH", "")
        env = {**os.environ, "LD_LIBRARY_PATH": os.pathsep.join([*libs, *([old] if old else [])])}
        return [sys.executable, str(tool), *args], env
    found = shutil.which("fastdds")
    if found is None:
        raise DiscoveryServerError(
            "no Fast DDS discovery tool: install ROS 2 (fastdds) or run from this project's venv"
        )
    return [found, *args], dict(os.environ)


_ANSI = re.compile(r"\x1b\[[0-9;]*m")


def _last_words(output: bytes) -> str:
    """The tool's last error (its log lines carry colour codes and a call site), else its last
    line."""
    lines = [_ANSI.sub("", x).strip() for x in output.decode(errors="replace").splitlines()]
    errors = [
        x.split("Error]", 1)[1].split(" -> Function")[0].strip() for x in lines if "Error]" in x
    ]
    said = errors[-1] if errors else next((x for x in reversed(lines) if x), "it said nothing")
    return said[:300]


class HostedServer:
    """The running server; :meth:`stop` ends it."""

    def __init__(self, host: str, port: int, timeout: float = START_TIMEOUT) -> None:
        argv, env = server_command(host, port)
        self.address = f"{host}:{port}"
        self._out = tempfile.TemporaryFile()  # noqa: SIM115 - what it says; closed by stop()
        self.proc = spawn(argv, stdout=self._out, stderr=subprocess.STDOUT, env=env)
        deadline = time.monotonic() + timeout
        while STARTED not in self.output():
            if time.monotonic() > deadline or self.proc.poll() is not None:
                words = _last_words(self.output())
                self.stop()
                raise DiscoveryServerError(
                    f"the discovery server on {self.address} did not start: {words}"
                )
            time.sleep(0.05)

    def output(self) -> bytes:
        return os.pread(self._out.fileno(), 8192, 0)

    def stop(self, timeout: float = 5.0) -> None:
        if self.proc.poll() is None:  # the tool and the server binary it runs: its group
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, signal.SIGINT)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
        self._out.close()
