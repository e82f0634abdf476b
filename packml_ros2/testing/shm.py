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
        # fds before maps: a file a process maps and then closes (open, mmap, close) is seen in
        # one or the other, whenever the scan comes by
        try:
            fds = list((proc / "fd").iterdir())
            for fd in fds:
                try:
                    target = os.readlink(fd)
                except FileNotFoundError:
                    continue  # closed meanwhile: that one file is no longer held through it
                except PermissionError:
                    raise  # (the process is not this user's: below)
                except OSError as exc:
                    raise _Unreadable(f"{fd}: {exc}") from None
                if target.startswith("/dev/shm/"):
                    used.add(target)
            maps = (proc / "maps").read_text()
        except (FileNotFoundError, ProcessLookupError):
            continue  # the process has ended: its files are not in use
        except PermissionError:
            continue  # not this user's to read at all (a sandbox's init): not a node it started
        except _Unreadable:
            raise
        except OSError as exc:
            raise _Unreadable(f"{proc}: {exc}") from None
        for line in maps.splitlines():
            if "/dev/shm/" in line:
                used.add(line[line.index("/dev/shm/") :].split(" (deleted)")[0])
    return used


#: Deleting a live participant's port files is what made readers deaf to writers on their graph
#: (the writers kept sending into the deleted port; subscribing again did not help, the port is
#: the participant's): the files are listed before the processes are scanned, each process's
#: fds before its maps. ``min_age``: seconds a file must have been left alone, for callers that
#: want a margin (the default removes a killed process's files at once, as Fast DDS prefers a
#: fresh port to a dead one it has to reclaim).
MIN_AGE = 0.0


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
    return [p for p in candidates if str(p) not in used and _age(p, now) >= min_age]


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
