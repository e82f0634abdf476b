"""The environment every packml_ros2 process should run with, and ROS domain allocation.

- ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``: DDS traffic never leaves the machine
  (``ROS_LOCALHOST_ONLY`` is ignored since Kilted).
- ``FASTDDS_DEFAULT_PROFILES_FILE``: quick discovery, transports on loopback and shared memory
  only (config/fastdds_loopback.xml).
- ``ROS_DOMAIN_ID``: a domain nobody else on this machine holds, so parallel runs (and pytest-xdist
  workers) never see each other; allocated with a lock file per domain.
"""

from __future__ import annotations

import fcntl
import os
import random
from pathlib import Path
from typing import IO

from ..paths import fastdds_profile

LOCK_DIR = Path(os.environ.get("PACKML_DOMAIN_LOCK_DIR", "/tmp/packml_ros2_domains"))
DOMAINS = range(10, 100)  # Fast DDS ports for 0..101 fit under 32768; keep 0..9 for people
_held: list[IO[str]] = []


def localhost_environment(env: dict[str, str] | None = None) -> dict[str, str]:
    """``env`` (default: os.environ) with the settings above; an explicit discovery range of
    LOCALHOST is enforced, other variables are only defaulted."""
    target = os.environ if env is None else env
    target["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    profile = fastdds_profile("LOCALHOST")  # transports on loopback only
    if profile.exists():
        target.setdefault("FASTDDS_DEFAULT_PROFILES_FILE", str(profile))
    return dict(target)


def allocate_domain() -> int:
    """Lock a ROS domain for the lifetime of this process and return it."""
    LOCK_DIR.mkdir(parents=True, exist_ok=True)
    candidates = list(DOMAINS)
    random.Random(os.getpid()).shuffle(candidates)
    for domain in candidates:
        handle = (LOCK_DIR / f"{domain}.lock").open("w")
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.close()
            continue
        handle.write(f"{os.getpid()}\n")
        handle.flush()
        _held.append(handle)
        return domain
    raise RuntimeError(f"no free ROS domain in {DOMAINS.start}..{DOMAINS.stop - 1} ({LOCK_DIR})")
