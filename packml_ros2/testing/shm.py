"""Fast DDS shared-memory leftovers: a SIGKILLed participant leaves ``/dev/shm/fastdds_*`` (and
``fastrtps_*``, ``sem.fastdds_*``) behind. Remove the ones no live process has open or mapped."""

from __future__ import annotations

import os
from pathlib import Path

SHM = Path("/dev/shm")
PATTERNS = ("fastdds_*", "fastrtps_*", "sem.fastdds_*", "sem.fastrtps_*")


def _in_use() -> set[str]:
    used: set[str] = set()
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            for line in (proc / "maps").read_text().splitlines():
                if "/dev/shm/" in line:
                    used.add(line[line.index("/dev/shm/") :].split(" (deleted)")[0])
            for fd in (proc / "fd").iterdir():
                target = os.readlink(fd)
                if target.startswith("/dev/shm/"):
                    used.add(target)
        except OSError:
            continue
    return used


def stale_files() -> list[Path]:
    used = _in_use()
    return [p for pattern in PATTERNS for p in SHM.glob(pattern) if str(p) not in used]


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
