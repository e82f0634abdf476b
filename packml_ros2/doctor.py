"""``packml doctor``: is this host fit to run PackML cells over DDS, and what to change if not.

Two halves. :func:`read_host` reads the host (environment, ``/proc/net/udp*``, ``/dev/shm``,
the kernel's clock state, the ephemeral port range) into a :class:`Host`, with no ROS import;
:data:`CHECKS` judges a :class:`Host` (and optionally a cell file's size) with pure functions, so
every verdict is testable from readings made by hand.

Where the numbers come from:

* Fast DDS ports (RTPS well-known ports): a participant ``p`` of domain ``d`` takes the unicast
  metatraffic port ``7400 + 250 d + 10 + 2 p`` and the user unicast port one above it; the domain's
  multicast discovery port is ``7400 + 250 d``. Counting the bound metatraffic ports of a domain
  counts its participants on this host (network namespace).
* More than about 100 DDS participants on one host may fail to discover each other (ROS 2
  documentation, "Large number of participants"; Fast DDS issues #5767, #6359); a domain has room
  for about 120 (the port block of 250).
* Fast DDS shared-memory segments in ``/dev/shm`` (``fastdds_*``) come with a ``*_el`` file whose
  ``flock`` their live owner holds: a segment whose lock is free belongs to a process that died
  (a SIGKILLed node) and only takes memory.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import fcntl
import json
import os
import re
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal
from xml.etree import ElementTree

PORT_BASE, DOMAIN_GAIN, PARTICIPANT_GAIN, METATRAFFIC_UNICAST = 7400, 250, 2, 10
SAFE_DOMAINS = range(102)  # ports of 0..101 stay under the usual ephemeral range (32768)
VALID_DOMAINS = range(233)
PARTICIPANT_WARN, PARTICIPANT_LIMIT = 80, 100
SHM_MIN_FREE = 64 << 20  # bytes: a participant maps about 0.5 MB, each port 52 kB
RANGES = ("LOCALHOST", "SUBNET", "OFF", "SYSTEM_DEFAULT")

Level = Literal["ok", "warn", "fail"]


@dataclass(frozen=True)
class ShmSegment:
    name: str
    size: int
    stale: bool  # nobody holds its lock: its process is gone


@dataclass(frozen=True)
class Host:
    """What :func:`read_host` read; every field plain data."""

    env: Mapping[str, str]
    udp_ports: frozenset[int]  # bound local UDP ports (IPv4 and IPv6)
    shm: tuple[ShmSegment, ...] = ()
    shm_free: int | None = None  # bytes free in /dev/shm; None: not mounted
    clock_synchronized: bool | None = None  # None: the kernel did not say
    ephemeral: tuple[int, int] = (32768, 60999)


@dataclass(frozen=True)
class CellSize:
    """What a cell file adds to the host: DDS participants when launched one way or the other."""

    cell: str
    units: int
    ems: int
    processes: int  # `packml launch --processes` / ros2 launch: one participant per node process
    in_process: int = 1  # `packml launch`: one process, one participant


@dataclass(frozen=True)
class Finding:
    check: str
    level: Level
    finding: str
    change: str = ""  # what to change; empty when nothing needs to


@dataclass
class Report:
    findings: list[Finding] = field(default_factory=list)

    @property
    def worst(self) -> Level:
        levels = {f.level for f in self.findings}
        return "fail" if "fail" in levels else "warn" if "warn" in levels else "ok"

    def to_json(self) -> str:
        return json.dumps(
            {"worst": self.worst, "findings": [asdict(f) for f in self.findings]}, indent=2
        )


# -- the checks ----------------------------------------------------------------------------


def domain_of(env: Mapping[str, str]) -> int | None:
    raw = env.get("ROS_DOMAIN_ID", "").strip()
    if not raw:
        return 0
    return int(raw) if raw.isdigit() else None


def participants(udp_ports: frozenset[int], also: int | None = None) -> dict[int, int]:
    """DDS participants per domain bound on this host (see the module's docstring): domains 0-101
    and ``also``; ports of higher domains are where the kernel also hands out ephemeral ports."""
    counts: dict[int, int] = {}
    for port in udp_ports:
        offset = port - PORT_BASE - METATRAFFIC_UNICAST
        domain, slot = divmod(offset, DOMAIN_GAIN)
        if (
            offset >= 0
            and (domain in SAFE_DOMAINS or domain == also)
            and slot % PARTICIPANT_GAIN == 0
        ):
            counts[domain] = counts.get(domain, 0) + 1
    return counts


def check_domain(host: Host, cell: CellSize | None) -> Finding:
    raw = host.env.get("ROS_DOMAIN_ID", "")
    domain = domain_of(host.env)
    if domain is None or domain not in VALID_DOMAINS:
        return Finding(
            "domain",
            "fail",
            f"ROS_DOMAIN_ID={raw!r} is not a domain (0-232)",
            "set ROS_DOMAIN_ID to a number from 0 to 101",
        )
    if domain not in SAFE_DOMAINS:
        return Finding(
            "domain",
            "warn",
            f"ROS_DOMAIN_ID={domain}: its DDS ports reach into the "
            "ephemeral port range, where other programs' sockets can take them",
            "use a domain from 0 to 101",
        )
    low, high = host.ephemeral
    first = PORT_BASE + DOMAIN_GAIN * domain
    if first + DOMAIN_GAIN > low and first <= high:
        return Finding(
            "domain",
            "warn",
            f"domain {domain}'s DDS ports {first}-{first + DOMAIN_GAIN - 1} "
            f"overlap the ephemeral port range {low}-{high}",
            "use a lower domain, or narrow net.ipv4.ip_local_port_range",
        )
    return Finding("domain", "ok", f"ROS_DOMAIN_ID={domain}" + ("" if raw else " (default)"))


def check_discovery(host: Host, cell: CellSize | None) -> Finding:
    env = host.env
    rng = env.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "").strip()
    server = env.get("ROS_DISCOVERY_SERVER", "").strip()
    peers = env.get("ROS_STATIC_PEERS", "").strip()
    if server:
        bad = [
            a
            for a in re.split(r"[;,]", server)
            if a and not re.fullmatch(r"[\w.\-]+(:\d{1,5})?", a.strip())
        ]
        if bad:
            return Finding(
                "discovery",
                "fail",
                f"ROS_DISCOVERY_SERVER has an address that is not host[:port]: {bad[0]!r}",
                "write it as host:port, several separated by ';'",
            )
        return Finding(
            "discovery",
            "ok",
            f"discovery server {server}"
            + (
                ""
                if env.get("ROS_SUPER_CLIENT")
                else "; the ros2 CLI needs ROS_SUPER_CLIENT=true to see the whole graph"
            ),
        )
    if rng and rng.upper() not in RANGES:
        return Finding(
            "discovery",
            "fail",
            f"ROS_AUTOMATIC_DISCOVERY_RANGE={rng!r} is not one of {', '.join(RANGES)}",
            "set ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST for a cell on this host",
        )
    rng = rng.upper()
    if rng == "LOCALHOST":
        note = f"; static peers {peers}" if peers else ""
        return Finding("discovery", "ok", f"LOCALHOST: DDS discovery stays on this host{note}")
    if rng == "OFF" and not peers:
        return Finding(
            "discovery",
            "warn",
            "discovery is OFF and there are no ROS_STATIC_PEERS: nodes find only themselves",
            "set ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST (one host) or name the peers",
        )
    if rng == "OFF":
        return Finding("discovery", "ok", f"discovery only with the static peers {peers}")
    return Finding(
        "discovery",
        "warn",
        f"ROS_AUTOMATIC_DISCOVERY_RANGE is {rng or 'unset'}: every node "
        "announces itself by multicast to the whole subnet, and any host there can command "
        "the cell",
        "set ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST for a cell on one host; across hosts, "
        "ROS_STATIC_PEERS or a discovery server (ROS_DISCOVERY_SERVER)",
    )


def check_profile(host: Host, cell: CellSize | None) -> Finding:
    name = next(
        (
            v
            for v in ("FASTDDS_DEFAULT_PROFILES_FILE", "FASTRTPS_DEFAULT_PROFILES_FILE")
            if host.env.get(v)
        ),
        None,
    )
    if name is None:
        return Finding(
            "profile", "ok", "no Fast DDS profile file: Fast DDS defaults (discovery can take 3 s)"
        )
    path = Path(host.env[name])
    try:
        if not path.is_file():
            return Finding(
                "profile",
                "fail",
                f"{name}={path} is not a file: every node ignores it",
                f"point {name} at an existing Fast DDS XML profile, or unset it",
            )
        if path.stat().st_size > 1 << 20:
            return Finding(
                "profile", "fail", f"{name}={path} is over 1 MB", "use a Fast DDS XML profile"
            )
        ElementTree.fromstring(path.read_bytes())  # the host's own file, size-bounded
    except (OSError, ElementTree.ParseError) as exc:
        return Finding(
            "profile",
            "fail",
            f"{name}={path} cannot be read as XML: {exc}",
            "fix or unset the profile file: Fast DDS refuses to start with it",
        )
    return Finding("profile", "ok", f"{name}={path}")


def check_participants(host: Host, cell: CellSize | None) -> Finding:
    domain = domain_of(host.env)
    by_domain = participants(host.udp_ports, domain)
    now = sum(by_domain.values())
    text = f"{now} DDS participant(s) on this host"
    if by_domain:
        text += " (" + ", ".join(f"domain {d}: {n}" for d, n in sorted(by_domain.items())) + ")"
    elif domain is not None:
        text += f" (domain {domain})"
    if cell:
        text += (
            f"; the cell {cell.cell} adds {cell.processes} with --processes or ros2 launch, "
            f"{cell.in_process} with packml launch"
        )
    total = now + (cell.processes if cell else 0)
    if total > PARTICIPANT_LIMIT:
        return Finding(
            "participants",
            "fail",
            f"{text}: {total} passes the ~{PARTICIPANT_LIMIT} at which participants on one host "
            "may fail to discover each other",
            "compose EMs into fewer processes (packml launch, or one process per robot "
            "controller), or spread cells over hosts",
        )
    if total > PARTICIPANT_WARN:
        return Finding(
            "participants",
            "warn",
            f"{text}: {total} is near the ~{PARTICIPANT_LIMIT} limit",
            "compose EMs into fewer processes, or spread cells over hosts",
        )
    return Finding("participants", "ok", text)


def check_shm(host: Host, cell: CellSize | None) -> Finding:
    if host.shm_free is None:
        return Finding(
            "shared memory",
            "warn",
            "/dev/shm is not mounted: Fast DDS falls back to UDP on this host",
            "mount a tmpfs on /dev/shm",
        )
    stale = [s for s in host.shm if s.stale]
    if stale:
        size = sum(s.size for s in stale)
        return Finding(
            "shared memory",
            "warn",
            f"{len(stale)} Fast DDS segment(s) in /dev/shm ({size / 1e6:.1f} MB) "
            "belong to processes that died (killed nodes leave them)",
            "remove them when no ROS process runs: `fastdds shm clean`, or `rm /dev/shm/fastdds_*` "
            "with every node stopped",
        )
    if host.shm_free < SHM_MIN_FREE:
        return Finding(
            "shared memory",
            "warn",
            f"only {host.shm_free / 1e6:.1f} MB free in /dev/shm",
            "free or enlarge /dev/shm (each node maps about 0.5 MB)",
        )
    return Finding(
        "shared memory",
        "ok",
        f"{host.shm_free / 1e6:.0f} MB free in /dev/shm, {len(host.shm)} live Fast DDS file(s)",
    )


def check_clock(host: Host, cell: CellSize | None) -> Finding:
    if host.clock_synchronized is None:
        return Finding("clock", "ok", "the kernel does not say whether the clock is synchronized")
    if not host.clock_synchronized:
        return Finding(
            "clock",
            "warn",
            "the system clock is not synchronized (NTP/PTP): stamps of "
            "transitions, alarms and bags from several hosts will not line up",
            "run an NTP or PTP client (chrony, systemd-timesyncd) on every host of the cell",
        )
    return Finding("clock", "ok", "the system clock is synchronized")


#: Every check, in the order the report lists them: (name, judge).
CHECKS: tuple[tuple[str, Callable[[Host, CellSize | None], Finding]], ...] = (
    ("discovery", check_discovery),
    ("domain", check_domain),
    ("profile", check_profile),
    ("participants", check_participants),
    ("shared memory", check_shm),
    ("clock", check_clock),
)


def diagnose(host: Host, cell: CellSize | None = None) -> Report:
    return Report([judge(host, cell) for _, judge in CHECKS])


# -- reading the host ----------------------------------------------------------------------


def udp_ports(proc: Path = Path("/proc/net")) -> frozenset[int]:
    ports: set[int] = set()
    for name in ("udp", "udp6"):
        try:
            lines = (proc / name).read_text(encoding="ascii").splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            if len(fields) > 1 and ":" in fields[1]:
                ports.add(int(fields[1].rsplit(":", 1)[1], 16))
    return frozenset(ports)


def shm_segments(shm: Path = Path("/dev/shm")) -> tuple[ShmSegment, ...]:
    """Fast DDS's segments and port files, each stale when nobody holds its ``_el`` lock."""
    found = []
    try:
        entries = sorted(
            p
            for p in shm.iterdir()
            if p.name.startswith(("fastdds_", "fastrtps_")) and not p.name.endswith("_el")
        )
    except OSError:
        return ()
    for seg in entries:
        lock = seg.with_name(seg.name + "_el")
        try:
            size = seg.stat().st_size
            fd = os.open(lock, os.O_RDONLY | os.O_NONBLOCK | os.O_NOFOLLOW)
        except OSError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            stale = False  # a live process holds it
        else:
            stale = True
            fcntl.flock(fd, fcntl.LOCK_UN)
        finally:
            os.close(fd)
        found.append(ShmSegment(seg.name, size, stale))
    return tuple(found)


class _Timex(ctypes.Structure):
    _fields_ = [
        ("modes", ctypes.c_uint),
        ("offset", ctypes.c_long),
        ("freq", ctypes.c_long),
        ("maxerror", ctypes.c_long),
        ("esterror", ctypes.c_long),
        ("status", ctypes.c_int),
        ("pad", ctypes.c_byte * 200),
    ]


STA_UNSYNC, TIME_ERROR = 0x0040, 5


def clock_synchronized() -> bool | None:
    """The kernel's NTP state (adjtimex with no change), None where it cannot be read."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
        tx = _Timex()
        state = int(libc.adjtimex(ctypes.byref(tx)))
    except (OSError, AttributeError):
        return None
    if state < 0:
        return None
    return not (state == TIME_ERROR or tx.status & STA_UNSYNC)


def ephemeral_range(proc: Path = Path("/proc/sys/net/ipv4/ip_local_port_range")) -> tuple[int, int]:
    try:
        low, high = proc.read_text(encoding="ascii").split()[:2]
        return int(low), int(high)
    except (OSError, ValueError):
        return (32768, 60999)


def read_host(env: Mapping[str, str] | None = None) -> Host:
    shm = Path("/dev/shm")
    try:
        st = os.statvfs(shm)
        free: int | None = st.f_bavail * st.f_frsize
    except OSError:
        free = None
    return Host(
        dict(os.environ if env is None else env),
        udp_ports(),
        shm_segments(shm),
        free,
        clock_synchronized(),
        ephemeral_range(),
    )
