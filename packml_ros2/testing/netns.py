"""Several "hosts" on one machine: network namespaces joined by veth pairs to a bridge namespace,
all private (nothing reaches the machine's own interfaces). Linux, root and iproute2.

    net = Network(["units", "ems"], subnet="10.213.0")
    net.setup()          # the bridge namespace, one namespace per host with eth0 at <subnet>.<i>
    net.cut("units")     # the host's link down (its bridge port), net.restore("units") up again
    net.teardown()       # kill what still runs in them and delete them (also after a failed setup)

Run a command in a host with :class:`NsProcess` (or ``[*net.exec_args(host), ...]``); inside, DDS needs
ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET (the namespaces' subnet is all there is) and, for a cut link to
matter, FASTDDS_BUILTIN_TRANSPORTS=UDPv4 (shared memory would bypass the network).
"""

from __future__ import annotations

import contextlib
import json
import os
import selectors
import shutil
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any


def ip(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    """``ip args``; a RuntimeError with its message when it fails (``check``)."""
    result = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=10, check=False)
    if check and result.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)}: {result.stderr.strip()}")
    return result


def why_no_namespaces() -> str:
    """Why network namespaces cannot be made here ('' = they can)."""
    if not sys.platform.startswith("linux"):
        return "network namespaces are Linux only"
    if shutil.which("ip") is None:
        return "iproute2 (ip) is not installed"
    if os.geteuid() != 0:
        return "creating network namespaces needs root"
    return ""


class Network:
    """The bridge and the hosts; ``cut(host)`` / ``restore(host)`` switch a host's link. Names
    carry ``prefix`` and this process's id, so parallel runs never meet."""

    def __init__(self, hosts: Sequence[str], subnet: str, prefix: str = "pk") -> None:
        tag = f"{prefix}{os.getpid() % 100000}"
        self.bridge = f"{tag}br"
        self.ns = {host: f"{tag}{host}" for host in hosts}
        # the bridge-side veth end: an interface name has at most 15 characters
        self.port = {host: f"{tag}p{i}" for i, host in enumerate(hosts)}
        self.address = {host: f"{subnet}.{i}" for i, host in enumerate(hosts, 1)}
        self.created: list[str] = []

    def setup(self) -> None:
        ip("netns", "add", self.bridge)
        self.created.append(self.bridge)
        ip("-n", self.bridge, "link", "add", "br0", "type", "bridge")
        ip("-n", self.bridge, "link", "set", "br0", "type", "bridge", "mcast_snooping", "0")
        ip("-n", self.bridge, "link", "set", "br0", "up")
        for host, ns in self.ns.items():
            port = self.port[host]
            ip("netns", "add", ns)
            self.created.append(ns)
            # both ends are created inside namespaces: nothing appears on the machine itself
            ip(
                "link",
                "add",
                port,
                "netns",
                self.bridge,
                "type",
                "veth",
                "peer",
                "name",
                "eth0",
                "netns",
                ns,
            )
            ip("-n", self.bridge, "link", "set", port, "master", "br0", "up")
            ip("-n", ns, "link", "set", "lo", "up")
            ip("-n", ns, "addr", "add", f"{self.address[host]}/24", "dev", "eth0")
            ip("-n", ns, "link", "set", "eth0", "up")
            ip("-n", ns, "route", "add", "224.0.0.0/4", "dev", "eth0")

    def cut(self, host: str) -> None:
        ip("-n", self.bridge, "link", "set", self.port[host], "down")

    def restore(self, host: str) -> None:
        ip("-n", self.bridge, "link", "set", self.port[host], "up")

    def exec_args(self, host: str) -> list[str]:
        return ["ip", "netns", "exec", self.ns[host]]

    def counters(self) -> dict[str, dict[str, int]]:
        """Per host, the bytes and packets its link carried (its bridge port's counters: what the
        host sent, what was delivered to it)."""
        links = json.loads(ip("-n", self.bridge, "-s", "-j", "link", "show").stdout)
        by_port = {link["ifname"]: link["stats64"] for link in links}
        out = {}
        for host, port in self.port.items():
            s = by_port[port]
            out[host] = {
                "sent_bytes": s["rx"]["bytes"],
                "sent_packets": s["rx"]["packets"],
                "delivered_bytes": s["tx"]["bytes"],
                "delivered_packets": s["tx"]["packets"],
            }
        return out

    def teardown(self) -> list[str]:
        """Kill what still runs in the namespaces (only processes their creator started can be
        there) and delete them; returns problems."""
        problems = []
        for ns in reversed(self.created):
            for pid in ip("netns", "pids", ns, check=False).stdout.split():
                with contextlib.suppress(ProcessLookupError, ValueError):
                    os.kill(int(pid), signal.SIGKILL)
                    problems.append(f"killed leftover process {pid} in {ns}")
            result = ip("netns", "del", ns, check=False)
            if result.returncode != 0:
                problems.append(f"ip netns del {ns}: {result.stderr.strip()}")
        self.created.clear()
        return problems


@contextlib.contextmanager
def private_network(hosts: Sequence[str], subnet: str, prefix: str = "pk") -> Iterator[Network]:
    """A :class:`Network` for one test, torn down after it (its problems printed); the test is
    skipped with the reason where namespaces cannot be made here."""
    import pytest

    reason = why_no_namespaces()
    if reason:
        pytest.skip(reason)
    net = Network(hosts, subnet, prefix)
    try:
        net.setup()
    except (RuntimeError, OSError, subprocess.TimeoutExpired) as exc:
        net.teardown()
        pytest.skip(f"cannot create network namespaces here: {exc}")
    try:
        yield net
    finally:
        for problem in net.teardown():
            print(problem)


class NsProcess:
    """``cmd`` inside ``host``'s namespace, in a session of its own, output to ``<log_dir>/<name>.log``.
    With ``pipe``, a peer that answers one JSON line on its stdout for each JSON request line on
    its stdin (:meth:`ask`) and ends at the end of its input."""

    def __init__(
        self,
        net: Network,
        host: str,
        name: str,
        cmd: Sequence[str],
        env: dict[str, str],
        log_dir: Path,
        pipe: bool = False,
        cwd: Path | None = None,
    ) -> None:
        self.name = name
        self.log = log_dir / f"{name}.log"
        self._log = self.log.open("ab")
        self.popen = subprocess.Popen(
            [*net.exec_args(host), *cmd],
            cwd=cwd,
            env=env,
            stdin=subprocess.PIPE if pipe else subprocess.DEVNULL,
            stdout=subprocess.PIPE if pipe else self._log,
            stderr=self._log,
            start_new_session=True,
            text=pipe,
        )
        self._selector = selectors.DefaultSelector()
        if pipe:
            assert self.popen.stdout is not None
            self._selector.register(self.popen.stdout, selectors.EVENT_READ)

    def running(self) -> bool:
        return self.popen.poll() is None

    def pids(self) -> list[int]:
        """This process (``ip netns exec`` execs the command: the pid is the command's) and its
        descendants."""
        found, todo = [], [self.popen.pid]
        while todo:
            pid = todo.pop()
            found.append(pid)
            for task in Path(f"/proc/{pid}/task").glob("*/children"):
                with contextlib.suppress(OSError, ValueError):
                    todo += [int(c) for c in task.read_text().split()]
        return found

    def ask(self, op: str, timeout: float = 20.0, **fields: Any) -> Any:
        """Send ``{"op": op, **fields}``; its answer (a RuntimeError for an ``error`` answer)."""
        assert self.popen.stdin is not None and self.popen.stdout is not None
        self.popen.stdin.write(json.dumps({"op": op, **fields}) + "\n")
        self.popen.stdin.flush()
        if not self._selector.select(timeout):
            raise TimeoutError(f"{self.name} did not answer {op} within {timeout:g} s")
        line = self.popen.stdout.readline()
        if not line:
            raise RuntimeError(f"{self.name} exited:\n{self.output()[-3000:]}")
        answer = json.loads(line)
        if isinstance(answer, dict) and "error" in answer:
            raise RuntimeError(f"{self.name} failed on {op}: {answer['error']}")
        return answer

    def stop(self, timeout: float = 5.0) -> int | None:
        """End of input (a peer), then SIGINT, then SIGKILL, to its whole session."""
        if self.running() and self.popen.stdin is not None:
            with contextlib.suppress(OSError):
                self.popen.stdin.close()
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.popen.wait(timeout)
        if self.running():  # as Ctrl-C would: its process group (a tool and the program it runs)
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.popen.pid, signal.SIGINT)
            try:
                self.popen.wait(timeout)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(self.popen.pid, signal.SIGKILL)
                self.popen.wait(5)
        self._log.close()
        return self.popen.returncode

    def output(self) -> str:
        if not self._log.closed:
            self._log.flush()
        return self.log.read_text(errors="replace")


def answer_requests(ops: dict[str, Callable[..., Any]]) -> None:
    """The peer side of :meth:`NsProcess.ask`: for each JSON line on stdin, ``ops[op](**fields)``
    answered as one JSON line on stdout (an exception: ``{"error": ...}``, and serving goes on),
    until the end of the input."""
    for line in sys.stdin:
        request = json.loads(line)
        op = request.pop("op", None)
        try:
            answer = ops[op](**request) if op in ops else {"error": f"unknown op {op!r}"}
        except Exception as exc:  # answer with the error, keep serving
            answer = {"error": repr(exc)}
        print(json.dumps(answer), flush=True)
