"""A program started in the background whose output is waited on line by line (no polling): a
thread copies its output (stdout and stderr) to a log file and wakes whoever waits for a pattern.
Used by the browser tests and the HMI benchmark for `packml launch <cell> --hmi`."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import threading
from collections.abc import Mapping
from pathlib import Path


class Launched:
    """``argv`` running (with ``env`` added to this process' environment), its output in ``log``
    (and :meth:`output`) as it comes."""

    def __init__(self, argv: list[str], log: Path, env: Mapping[str, str] | None = None) -> None:
        self.argv = list(argv)
        self.log = log
        self._out = log.open("wb")
        self._text: list[str] = []
        self._ended = False
        self._changed = threading.Condition()
        self.proc = subprocess.Popen(
            argv,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
        )
        self._reader = threading.Thread(target=self._read, name="launched-output", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in iter(self.proc.stdout.readline, b""):
            self._out.write(line)
            self._out.flush()
            with self._changed:
                self._text.append(line.decode(errors="replace"))
                self._changed.notify_all()
        with self._changed:  # the end of the output: the program has exited
            self._ended = True
            self._changed.notify_all()

    def output(self) -> str:
        with self._changed:
            return "".join(self._text)

    def wait_for(self, pattern: str, timeout: float = 60.0) -> re.Match[str]:
        """The first match of ``pattern`` in the output, waiting for the line that has it; raises
        AssertionError when the program ends or ``timeout`` passes first."""
        found: list[re.Match[str]] = []

        def seen() -> bool:
            match = re.search(pattern, "".join(self._text))
            if match:
                found.append(match)
            return bool(match) or self._ended

        with self._changed:
            ended = self._changed.wait_for(seen, timeout)
        if found:
            return found[0]
        if ended:
            self.proc.wait(5)
            command = " ".join(self.argv)
            raise AssertionError(f"{command} exited {self.proc.returncode}:\n{self.output()}")
        raise AssertionError(f"{pattern!r} not within {timeout} s:\n{self.output()}")

    def stop(self, timeout: float = 20.0) -> int:
        """Ctrl-C, then (after ``timeout``) kill; its exit code."""
        self.proc.send_signal(signal.SIGINT)
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            return self.proc.wait()
        finally:
            self._reader.join(5)
            self._out.close()
