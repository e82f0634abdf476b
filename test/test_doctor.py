"""``packml doctor``: the verdicts from readings made by hand, then the real command on hosts the
test makes (a new network and mount namespace with its own /dev/shm): a healthy one, one with more
DDS participants than a host carries, and one where a killed ROS node left its shared memory."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from packml_ros2.doctor import (
    PORT_BASE,
    CellSize,
    Host,
    ShmSegment,
    diagnose,
    participants,
    udp_ports,
)

ROOT = Path(__file__).resolve().parents[1]
LOCAL = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": "7"}


def port(domain: int, participant: int) -> int:
    return PORT_BASE + 250 * domain + 10 + 2 * participant


def verdict(host: Host, cell: CellSize | None = None) -> dict[str, tuple[str, str, str]]:
    return {f.check: (f.level, f.finding, f.change) for f in diagnose(host, cell).findings}


def test_a_local_host_with_a_few_participants_has_nothing_to_change() -> None:
    ports = frozenset({port(7, 0), port(7, 0) + 1, port(7, 1), port(7, 1) + 1, 40000})
    host = Host(LOCAL, ports, (ShmSegment("fastdds_port7411", 52400, False),), 1 << 30, True)
    report = diagnose(host)
    assert report.worst == "ok", report.findings
    assert "2 DDS participant(s) on this host (domain 7: 2)" in verdict(host)["participants"][1]


@pytest.mark.parametrize(
    ("env", "level", "words"),
    [
        ({}, "warn", "multicast to the whole subnet"),
        ({"ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"}, "warn", "any host there can command"),
        ({"ROS_AUTOMATIC_DISCOVERY_RANGE": "everywhere"}, "fail", "is not one of"),
        ({"ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF"}, "warn", "nodes find only themselves"),
        ({"ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF", "ROS_STATIC_PEERS": "10.0.0.2"}, "ok", "static"),
        ({"ROS_DISCOVERY_SERVER": "127.0.0.1:11811"}, "ok", "ROS_SUPER_CLIENT=true"),
        ({"ROS_DISCOVERY_SERVER": "127.0.0.1:11811 rm -rf"}, "fail", "not host[:port]"),
        ({"ROS_AUTOMATIC_DISCOVERY_RANGE": "localhost"}, "ok", "stays on this host"),
    ],
)
def test_discovery_settings(env: dict[str, str], level: str, words: str) -> None:
    got = verdict(Host(env, frozenset()))["discovery"]
    assert got[0] == level and words in got[1], got
    assert bool(got[2]) == (level != "ok")


@pytest.mark.parametrize(
    ("domain", "ephemeral", "level", "words"),
    [
        ("7", (32768, 60999), "ok", "ROS_DOMAIN_ID=7"),
        ("", (32768, 60999), "ok", "(default)"),
        ("abc", (32768, 60999), "fail", "is not a domain"),
        ("233", (32768, 60999), "fail", "is not a domain"),
        ("150", (32768, 60999), "warn", "ephemeral port range"),
        ("100", (30000, 60999), "warn", "overlap the ephemeral port range 30000-60999"),
    ],
)
def test_the_domain_and_its_ports(
    domain: str, ephemeral: tuple[int, int], level: str, words: str
) -> None:
    got = verdict(Host({"ROS_DOMAIN_ID": domain}, frozenset(), ephemeral=ephemeral))["domain"]
    assert got[0] == level and words in got[1], got


def test_participants_against_the_limit_per_host_across_domains() -> None:
    def ports(n: int, domain: int) -> set[int]:
        return {port(domain, p) for p in range(n)} | {port(domain, p) + 1 for p in range(n)}

    assert participants(frozenset(ports(30, 3) | ports(40, 9))) == {3: 30, 9: 40}
    assert verdict(Host(LOCAL, frozenset(ports(70, 7))))["participants"][0] == "ok"
    near = verdict(Host(LOCAL, frozenset(ports(50, 7) | ports(35, 8))))["participants"]
    assert near[0] == "warn" and "85 is near the ~100 limit" in near[1], near
    over = verdict(Host(LOCAL, frozenset(ports(101, 7))))["participants"]
    assert over[0] == "fail" and "101 passes the ~100" in over[1] and "compose EMs" in over[2]
    # A cell file's processes are counted in: 75 here + a cell of 30 processes is over.
    cell = CellSize("big", units=3, ems=26, processes=30)
    counted = verdict(Host(LOCAL, frozenset(ports(75, 7))), cell)["participants"]
    assert counted[0] == "fail" and "the cell big adds 30" in counted[1], counted


def test_the_fast_dds_profile_is_checked(tmp_path: Path) -> None:
    def level(path: Path | str) -> tuple[str, str, str]:
        env = {**LOCAL, "FASTDDS_DEFAULT_PROFILES_FILE": str(path)}
        return verdict(Host(env, frozenset()))["profile"]

    assert level(ROOT / "config" / "fastdds_localhost.xml")[0] == "ok"
    assert level(tmp_path / "missing.xml")[:2] == (
        "fail",
        f"FASTDDS_DEFAULT_PROFILES_FILE={tmp_path / 'missing.xml'} is not a file: every node "
        "ignores it",
    )
    broken = tmp_path / "broken.xml"
    broken.write_text("<dds><profiles>")
    assert level(broken)[0] == "fail" and "cannot be read as XML" in level(broken)[1]


def test_shared_memory_and_clock() -> None:
    stale = (ShmSegment("fastdds_1a2b", 549408, True), ShmSegment("fastdds_port7411", 52400, True))
    got = verdict(Host(LOCAL, frozenset(), stale, 1 << 30, True))
    assert got["shared memory"][0] == "warn" and "2 Fast DDS segment(s)" in got["shared memory"][1]
    assert verdict(Host(LOCAL, frozenset(), (), 10 << 20))["shared memory"][0] == "warn"
    assert verdict(Host(LOCAL, frozenset(), (), None))["shared memory"][0] == "warn"
    assert verdict(Host(LOCAL, frozenset(), clock_synchronized=False))["clock"][0] == "warn"
    assert verdict(Host(LOCAL, frozenset(), clock_synchronized=None))["clock"][0] == "ok"


def test_udp_ports_are_read_from_proc(tmp_path: Path) -> None:
    (tmp_path / "udp").write_text(
        "  sl  local_address rem_address   st\n"
        "   0: 00000000:1CE2 00000000:0000 07\n"
        "   1: 0100007F:1CE3 00000000:0000 07\n"
    )
    (tmp_path / "udp6").write_text(
        "  sl  local_address rem_address   st\n"
        "   0: 00000000000000000000000000000000:1CE4 00000000000000000000000000000000:0000 07\n"
    )
    assert udp_ports(tmp_path) == {0x1CE2, 0x1CE3, 0x1CE4}


# -- the real command on hosts the test makes ----------------------------------------------------------

netns = pytest.mark.skipif(
    os.geteuid() != 0 or shutil.which("unshare") is None,
    reason="needs root and unshare (util-linux) to make a host of its own",
)

#: Runs in a new network and mount namespace: loopback up, a tmpfs of its own on /dev/shm.
HOST = textwrap.dedent(
    """
    import json, os, socket, subprocess, sys, time
    subprocess.run(["ip", "link", "set", "lo", "up"], check=True)
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256m", "tmpfs", "/dev/shm"], check=True)
    def doctor(*args):
        out = subprocess.run([sys.executable, "-m", "packml_ros2.cli.main", "doctor", "--json", *args],
                             check=False, capture_output=True, text=True, timeout=60)
        return {"rc": out.returncode, **json.loads(out.stdout)}
    """
)


#: A real ROS node that stays up until its standard input closes.
PROBE = (
    "import rclpy, std_msgs.msg, sys\n"
    "rclpy.init()\n"
    "n = rclpy.create_node('doctor_probe')\n"
    "n.create_publisher(std_msgs.msg.String, 'probe', 10)\n"
    "print('up', flush=True)\n"
    "sys.stdin.read()\n"
)


def on_a_host_of_its_own(script: str) -> dict[str, dict[str, object]]:
    """Each line ``RESULT <name> <json>`` the script prints, by name."""
    env = {**os.environ, **LOCAL}
    out = subprocess.run(
        ["unshare", "--net", "--mount", "--fork", sys.executable, "-c",
         HOST + f"PROBE = {PROBE!r}\n" + script],
        check=False, capture_output=True, text=True, timeout=120, cwd=ROOT, env=env,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr[-3000:]
    results = {}
    for line in out.stdout.splitlines():
        if line.startswith("RESULT "):
            _, name, payload = line.split(" ", 2)
            results[name] = json.loads(payload)
    return results


def by_check(result: dict[str, object]) -> dict[str, dict[str, str]]:
    findings = result["findings"]
    assert isinstance(findings, list)
    return {f["check"]: f for f in findings}


@netns
@pytest.mark.ros
def test_a_killed_node_leaves_shared_memory_the_doctor_finds() -> None:
    results = on_a_host_of_its_own(
        textwrap.dedent(
            """
            print("RESULT empty " + json.dumps(doctor()))
            node = subprocess.Popen([sys.executable, "-c", PROBE], stdin=subprocess.PIPE,
                                    stdout=subprocess.PIPE, text=True)
            assert node.stdout.readline().strip() == "up"
            print("RESULT alive " + json.dumps(doctor()))
            node.kill(); node.wait()
            print("RESULT killed " + json.dumps(doctor()))
            """
        )
    )
    empty, alive, killed = (by_check(results[k]) for k in ("empty", "alive", "killed"))
    assert empty["shared memory"]["level"] == "ok"
    assert empty["participants"]["finding"].startswith("0 DDS participant(s) on this host")
    assert alive["shared memory"]["level"] == "ok", alive["shared memory"]
    assert alive["participants"]["finding"].startswith(
        "1 DDS participant(s) on this host (domain 7: 1)"
    )
    assert killed["shared memory"]["level"] == "warn", killed["shared memory"]
    assert "belong to processes that died" in killed["shared memory"]["finding"]
    assert killed["participants"]["finding"].startswith("0 DDS participant(s)")


@netns
def test_a_host_with_more_participants_than_it_carries_is_refused_with_what_to_change() -> None:
    results = on_a_host_of_its_own(
        textwrap.dedent(
            """
            base = 7400 + 250 * 7 + 10
            held = []
            for p in range(101):  # what 101 DDS participants of domain 7 bind
                for port in (base + 2 * p, base + 2 * p + 1):
                    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                    s.bind(("127.0.0.1", port))
                    held.append(s)
            print("RESULT crowded " + json.dumps(doctor()))
            print("RESULT cell " + json.dumps(doctor("config/demo_cell.yaml")))
            for s in held[:120]:  # 60 participants leave
                s.close()
            print("RESULT relieved " + json.dumps(doctor("config/demo_cell.yaml")))
            """
        )
    )
    crowded = results["crowded"]
    assert crowded["rc"] == 1 and crowded["worst"] == "fail"
    got = by_check(crowded)["participants"]
    assert (
        got["level"] == "fail"
        and "101 DDS participant(s) on this host (domain 7: 101)" in got["finding"]
    )
    assert "compose EMs into fewer processes" in got["change"]
    cell = by_check(results["cell"])["participants"]
    assert (
        "the cell demo_cell adds 10 with --processes or ros2 launch, 1 with packml launch"
        in cell["finding"]
    )
    relieved = by_check(results["relieved"])["participants"]
    assert relieved["level"] == "ok" and "41 DDS participant(s)" in relieved["finding"], relieved


def test_the_command_says_what_to_change_and_exits_1_and_refuses_a_bad_cell(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if k != "ROS_AUTOMATIC_DISCOVERY_RANGE"}
    out = subprocess.run([sys.executable, "-m", "packml_ros2.cli.main", "doctor"], env=env,
                         check=False, capture_output=True, text=True, timeout=60, cwd=ROOT)  # fmt: skip
    assert out.returncode == 1, out
    assert "WARN  discovery: ROS_AUTOMATIC_DISCOVERY_RANGE is unset" in out.stdout
    assert "-> set ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST" in out.stdout
    assert "Traceback" not in out.stderr
    bad = tmp_path / "bad.yaml"
    bad.write_text("cell: x\nunits: 3\n")
    out = subprocess.run([sys.executable, "-m", "packml_ros2.cli.main", "doctor", str(bad)],
                         check=False, capture_output=True, text=True, timeout=60, cwd=ROOT)  # fmt: skip
    assert (
        out.returncode == 2
        and out.stderr.startswith("packml doctor: ")
        and "Traceback" not in out.stderr
    )
