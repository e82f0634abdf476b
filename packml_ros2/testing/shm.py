"""Fast DDS shared-memory leftovers: a SIGKILLed participant leaves ``/dev/shm/fastdds_*`` (and
``fastrtps_*``, ``sem.fastdds_*``) behind. Remove the ones no live process has open or mapped."""

from __future__ import annotations

import os
import time
from pathlib import Path

SHM = Path("/dev/shm")
PATTERNS = ("fastdds_*", "fastrtps_*", "sem.fastdds_*", "sem.fastrtps_*")


class _Unreadable(Exception):
    """A live process whose open files could not all be read."""


def _in_use() -> set[str]:
    """Every /dev/shm file some process has mapped or open. Raises :class:`_Unreadable` when a
    live process could not be read whole: a file of it might be missed, and a live participant's
    port whose lock file is deleted is taken over by the next participant that starts (its
    senders then reach nobody: a restarted node that nobody hears)."""
    used: set[str] = set()
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            maps = (proc / "maps").read_text()
            fds = list((proc / "fd").iterdir())
        except (FileNotFoundError, ProcessLookupError):
            continue  # the process has ended: its files are not in use
        except PermissionError:
            continue  # not this user's to read at all (a sandbox's init): not a node it started
        except OSError as exc:
            raise _Unreadable(f"{proc}: {exc}") from None
        for line in maps.splitlines():
            if "/dev/shm/" in line:
                used.add(line[line.index("/dev/shm/") :].split(" (deleted)")[0])
        for fd in fds:
            try:
                target = os.readlink(fd)
            except FileNotFoundError:
                continue  # closed meanwhile: that one file is no longer held through it
            except OSError as exc:
                raise _Unreadable(f"{fd}: {exc}") from None
            if target.startswith("/dev/shm/"):
                used.add(target)
    return used


#: Seconds a file must have been left alone before it can be stale: a participant that is
#: starting while the processes are scanned may have made its files and not yet opened or
#: mapped them where the scan looked. (Deleting a live participant's port files is what made
#: readers deaf to writers on their graph: the writer kept sending into the old, deleted
#: segment; subscribing again did not help, the port is the participant's.)
MIN_AGE = 10.0


def _age(path: Path, now: float) -> float:
    try:
        st = path.stat()
    except FileNotFoundError:
        return 0.0
    return now - max(st.st_mtime, st.st_ctime)


def stale_files(min_age: float = MIN_AGE) -> list[Path]:
    """The Fast DDS files no process holds and nothing changed for ``min_age`` seconds; none
    when that cannot be known for sure. The files are listed before the processes are scanned:
    a file made during the scan is not a candidate at all."""
    candidates = [p for pattern in PATTERNS for p in SHM.glob(pattern)]
    try:
        used = _in_use()
    except _Unreadable:
        return []
    now = time.time()
    stale = [p for p in candidates if str(p) not in used and _age(p, now) >= min_age]
    gone = set(stale)
    return [p for p in stale if not _lives_on(p, gone)]


def _lives_on(path: Path, gone: set[Path]) -> bool:
    """Whether ``path`` is a named mutex (``sem.<segment>_mutex``) whose segment stays. Fast DDS
    holds a port's mutex neither open nor mapped between uses (seen: every live port's
    ``sem.fastdds_port<N>_mutex`` free of every process), so it goes with its segment only:
    removed under a live port, the next participant to open that port would meet a port without
    its mutex. (Looked at for a restarted unit that neither its EM nor the test heard, in CI;
    deleting the mutexes alone did not make a restarted writer unheard here.)"""
    name = path.name
    if not (name.startswith("sem.") and name.endswith("_mutex")):
        return False
    segment = path.with_name(name[len("sem.") : -len("_mutex")])
    return segment.exists() and segment not in gone


def cleanup() -> int:
    """Remove stale Fast DDS shared-memory files; returns how many were removed."""
    removed = 0
    for path in stale_files():
        try:
            path.unlink()
            removed += 1
        except OSError:
            pass
    return removed
