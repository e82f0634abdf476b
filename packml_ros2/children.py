"""Child processes that end with the process that started them.

``packml launch`` starts each node in a session of its own, so that Ctrl-C reaches the launcher
alone and it stops the nodes in order. The other side of that: a launcher killed outright
(SIGKILL, the OOM killer, a crashed terminal) used to leave its nodes running, and a second
launch of the same cell then met a second unit of the same name. :func:`spawn` asks Linux to send
the child SIGINT - the launcher's own clean stop - when its parent dies
(``prctl(PR_SET_PDEATHSIG)``), and stops a child whose parent died before it could ask.

Linux ties that signal to the thread that forked, not to the process: only the main thread,
which lives as long as the process, asks for it.
"""

from __future__ import annotations

import ctypes
import functools
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Callable, Sequence
from typing import Any

PR_SET_PDEATHSIG = 1
#: what a child receives when its parent dies: the clean stop the launcher itself would send
PARENT_DEATH_SIGNAL = signal.SIGINT


@functools.cache
def _prctl() -> Any:
    """libc's prctl, looked up once (None where there is none: not Linux)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None
    prctl.argtypes = [ctypes.c_int, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong]
    prctl.restype = ctypes.c_int
    return prctl


def _guard(parent: int) -> Callable[[], None] | None:
    """The function the child runs between fork and exec (None where Linux has no prctl)."""
    prctl = _prctl()
    if prctl is None or threading.current_thread() is not threading.main_thread():
        return None
    signum = int(PARENT_DEATH_SIGNAL)

    def in_child() -> None:  # (after fork: no allocation, no lock, nothing imported)
        prctl(PR_SET_PDEATHSIG, signum, 0, 0, 0)
        if os.getppid() != parent:  # the parent died before the request: as if after it
            os.kill(os.getpid(), signum)

    return in_child


def spawn(argv: Sequence[str], **options: Any) -> subprocess.Popen[bytes]:
    """``subprocess.Popen(argv, start_new_session=True, **options)``, the child ending (SIGINT)
    when this process dies."""
    # (preexec_fn with threads: the child only calls prctl, getppid and kill, holding the GIL
    # it forked with; glibc's malloc is fork-safe)
    guard = _guard(os.getpid())
    return subprocess.Popen(list(argv), start_new_session=True, preexec_fn=guard, **options)  # noqa: PLW1509
