"""Issue 5: `packml launch` (one process and one process per node, clean Ctrl-C) and the `packml`
verbs, as a user runs them: real subprocesses against a real cell."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from .cells import saved_admin, saved_faults, shutdown_noise

PACKML = [sys.executable, "-m", "packml_ros2.cli.main"]
FAST = {"resetting": 0.1, "starting": 0.1, "stopping": 0.1, "clearing": 0.1, "aborting": 0.05}


def cell_file(tmp_path: Path, name: str) -> Path:
    doc = {
        "cell": name,
        "defaults": {"remote_commands_enabled": True},
        "units": {
            "filler": {
                "persistence": {"path": str(tmp_path / "filler.sqlite3")},
                "counters": {"processed": [{"id": 1, "name": "bottles"}]},
                "alarms": [{"id": 201, "message": "Nozzle clogged", "category": 2, "em": "nozzle"}],
                "equipment_modules": {
                    "nozzle": {"sim": {"durations": FAST, "cycle_time": 0.1,
                                       "faults": {"clog": {"kind": "alarm", "alarm_id": 201}}}},
                    "conveyor": {"sim": {"durations": FAST, "cycle_time": 0.2, "counter": "none"}},
                },
            },
            "capper": {
                "persistence": {"path": str(tmp_path / "capper.sqlite3")},
                "equipment_modules": {"chuck": {"sim": {"durations": FAST, "cycle_time": 0.2}}},
            },
        },
        "coordinator": {"start_order": ["capper", "filler"], "stop_order": ["filler", "capper"]},
    }  # fmt: skip
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


class Launched:
    """`packml launch` running in the background; its output collected line by line."""

    def __init__(self, args: list[str], log: Path) -> None:
        self.log = log
        self._out = log.open("wb")
        self.proc = subprocess.Popen(
            [*PACKML, "launch", *args],
            stdout=self._out,
            stderr=subprocess.STDOUT,
            env=dict(os.environ, PYTHONUNBUFFERED="1"),
        )

    def output(self) -> str:
        return self.log.read_text(errors="replace")

    def wait_ready(self, timeout: float = 60.0) -> str:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            text = self.output()
            if "is up" in text:
                return text
            if self.proc.poll() is not None:
                raise AssertionError(f"packml launch exited {self.proc.returncode}:\n{text}")
            time.sleep(0.05)
        raise AssertionError(f"not ready within {timeout} s:\n{self.output()}")

    def ctrl_c(self, timeout: float = 20.0) -> int:
        self.before_ctrl_c = len(self.output())
        self.ctrl_c_at = time.time()
        self.proc.send_signal(signal.SIGINT)
        try:
            return self.proc.wait(timeout)
        finally:
            self._out.close()

    def after_ctrl_c(self) -> str:
        return self.output()[self.before_ctrl_c :]


def assert_quiet_shutdown_without_fault(launch: Launched, tmp_path: Path) -> None:
    """After Ctrl-C in Execute: only the goodbye lines of every node (2 units, 3 EMs, the
    coordinator), and each unit's saved admin data holds no fault: its StopReason is its own
    shutdown, the alarm history has no alarm (no "EM ... lost")."""
    after = launch.after_ctrl_c()
    assert not shutdown_noise(after), after
    assert after.count("shut down (SIGINT)") == 3 and after.count("left unit") == 3, after
    for unit in ("filler", "capper"):
        saved = saved_admin(tmp_path / f"{unit}.sqlite3", unit)
        assert not saved_faults(saved, launch.ctrl_c_at), (unit, saved_faults(saved), after)
        assert saved["stop_reason"]["message"] == "unit shut down (SIGINT) in EXECUTE"


#: Prints the node names on the graph once the node argv[1] is seen and the set has not changed
#: for 10 polls (an absence can only be checked against a settled graph).
NODE_NAMES = """
import sys, time, rclpy
rclpy.init()
node = rclpy.create_node("node_names")
seen, stable, deadline = set(), 0, time.monotonic() + 20
while (sys.argv[1] not in seen or stable < 10) and time.monotonic() < deadline:
    now = {ns.rstrip("/") + "/" + n for n, ns in node.get_node_names_and_namespaces()}
    stable = stable + 1 if now == seen else 0
    seen = now
    time.sleep(0.05)
print("\\n".join(sorted(seen)))
"""


def packml(*args: str, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*PACKML, *args], check=False, capture_output=True, text=True, timeout=timeout
    )


def wait_for(
    args: tuple[str, ...], text: str, timeout: float = 15.0
) -> subprocess.CompletedProcess[str]:
    deadline = time.monotonic() + timeout
    while True:
        result = packml(*args)
        if text in result.stdout or time.monotonic() > deadline:
            return result


@pytest.fixture
def launched(tmp_path: Path):
    name = f"cli{os.getpid()}"
    launch = Launched([str(cell_file(tmp_path, name))], tmp_path / "launch.log")
    launch.wait_ready()
    yield name, launch
    if launch.proc.poll() is None:
        launch.proc.kill()


def test_launch_in_one_process_and_the_cli_verbs(launched, tmp_path: Path) -> None:
    cell, launch = launched
    ready = launch.output()
    assert f"packml cmd {cell} reset" in ready and "ros2 topic echo" in ready  # what to try

    # the verbs answer as soon as the cell is complete (the coordinator lists its units), not at
    # the end of their discovery timeout (they did: 5 s every time; bench/cli.py measures it)
    for verb in (("status",), ("status", "filler"), ("alarms",)):
        t0 = time.monotonic()
        status = packml(*verb, "--timeout", "30")
        took = time.monotonic() - t0
        assert status.returncode == 0, status.stderr
        assert took < 15, f"packml {' '.join(verb)} took {took:.1f} s"
    status = packml("status")
    assert status.returncode == 0, status.stderr
    assert "filler" in status.stdout and "capper" in status.stdout and "STOPPED" in status.stdout

    # the whole cell through the coordinator, in the configured order (downstream first)
    reset = packml("cmd", cell, "reset")
    assert reset.returncode == 0, reset.stdout + reset.stderr
    assert reset.stdout.index("capper") < reset.stdout.index("filler")
    start = packml("cmd", cell, "2")  # numbers are accepted too
    assert start.returncode == 0, start.stdout + start.stderr
    # the launcher's probe is gone once the cell is up: the graph shows the cell's nodes only
    nodes = subprocess.run(
        [sys.executable, "-c", NODE_NAMES, f"/{cell}/coordinator"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    assert f"/{cell}/coordinator" in nodes and "packml_launch_probe" not in nodes, nodes

    # a refusal: exit code 1 and the reason
    again = packml("cmd", "filler", "start")
    assert again.returncode == 1
    assert "START not allowed in EXECUTE" in again.stdout + again.stderr
    mode = packml("mode", "filler", "maintenance")
    assert mode.returncode == 1 and "not allowed in EXECUTE" in mode.stdout + mode.stderr

    detail = wait_for(("status", f"{cell}/filler"), "bottles: ", 10)
    assert "EXECUTE" in detail.stdout and "nozzle" in detail.stdout

    # a simulated fault: category 2 -> the filler stops; the alarm is listed, acknowledged, reset
    assert packml("fault", "filler/nozzle", "clog", "on").returncode == 0
    alarms = wait_for(("alarms", "list", "filler"), "Nozzle clogged")
    assert "201" in alarms.stdout and "ACTIVE" in alarms.stdout
    # the forms people type (issue 24: usage errors before), the same list and the history
    typed = packml("alarms", "filler")
    assert typed.returncode == 0 and typed.stdout == alarms.stdout, typed.stdout + typed.stderr
    history = packml("alarms", "--history", "filler")
    assert history.returncode == 0 and "filler:" in history.stdout, history.stdout + history.stderr
    assert "Nozzle clogged" in history.stdout
    stopped = wait_for(("status", "filler"), "STOPPED")
    assert "STOPPED" in stopped.stdout
    refused = packml("cmd", "filler", "reset")
    assert refused.returncode == 1 and "Nozzle clogged" in refused.stdout + refused.stderr
    assert packml("fault", "filler/nozzle", "clog", "off").returncode == 0
    ack = packml("alarms", "ack", "filler")
    assert ack.returncode == 0, ack.stdout + ack.stderr
    assert packml("cmd", "filler", "reset").returncode == 0

    watch = packml("watch", "--frames", "2", "--plain")
    assert watch.returncode == 0, watch.stderr
    assert watch.stdout.count(cell) >= 2 and "filler" in watch.stdout

    assert packml("cmd", "filler", "start").returncode == 0
    assert launch.ctrl_c() == 0, launch.output()[-2000:]
    assert_quiet_shutdown_without_fault(launch, tmp_path)


def test_launch_one_process_per_node_and_ctrl_c(tmp_path: Path) -> None:
    name = f"proc{os.getpid()}"
    launch = Launched(["--processes", str(cell_file(tmp_path, name))], tmp_path / "launch.log")
    try:
        ready = launch.wait_ready()
        assert "6 processes" in ready  # 2 units, 3 EMs, the coordinator
        for command in ("reset", "start"):
            result = packml("cmd", name, command)
            assert result.returncode == 0, result.stdout + result.stderr
        children = subprocess.run(
            ["pgrep", "-f", f"{name}.yaml"], check=False, capture_output=True, text=True
        ).stdout.split()
        assert len([c for c in children if int(c) != launch.proc.pid]) == 6
        assert launch.ctrl_c() == 0, launch.output()[-2000:]
        assert_quiet_shutdown_without_fault(launch, tmp_path)
        left = subprocess.run(
            ["pgrep", "-f", f"{name}.yaml"], check=False, capture_output=True, text=True
        ).stdout.split()
        assert not left, f"processes left behind: {left}"
    finally:
        if launch.proc.poll() is None:
            launch.proc.kill()
        subprocess.run(["pkill", "-9", "-f", f"{name}.yaml"], check=False)


def _running(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie nobody reaped yet has ended)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def test_a_launcher_killed_outright_takes_its_nodes_with_it(tmp_path: Path) -> None:
    """SIGKILL leaves the launcher no time to stop its nodes: each node, in a session of its own,
    gets SIGINT from Linux when the launcher dies (packml_ros2.children) and stops cleanly."""
    name = f"orph{os.getpid()}"
    launch = Launched(["--processes", str(cell_file(tmp_path, name))], tmp_path / "launch.log")
    try:
        launch.wait_ready()
        nodes = [int(c) for c in subprocess.run(["pgrep", "-f", f"{name}.yaml"], check=False,
                 capture_output=True, text=True).stdout.split() if int(c) != launch.proc.pid]  # fmt: skip
        assert len(nodes) == 6
        launch.proc.kill()
        launch.proc.wait()
        deadline = time.monotonic() + 30  # (a node ends itself within run.TEARDOWN_LIMIT)
        while time.monotonic() < deadline and any(_running(pid) for pid in nodes):
            time.sleep(0.1)
        left = [pid for pid in nodes if _running(pid)]
        assert not left, f"nodes left behind by a killed launcher: {left}"
    finally:
        subprocess.run(["pkill", "-9", "-f", f"{name}.yaml"], check=False)


def test_bad_configuration_fails_at_start_naming_the_key(tmp_path: Path) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(
        "cell: bad\nunits:\n  u:\n    equipment_modules:\n      e: {sim: {durations: {starting: -1}, cycle_tim: 2}}\n"
    )
    result = packml("launch", "--check", str(path))
    assert result.returncode == 2
    assert "units.u.equipment_modules.e.sim.durations.starting" in result.stderr
    assert "cycle_tim" in result.stderr and "did you mean 'cycle_time'" in result.stderr


@pytest.mark.parametrize("verb", ["launch", "status", "cmd", "mode", "alarms", "watch", "fault"])
def test_every_verb_has_help(verb: str) -> None:
    result = packml(verb, "--help")
    assert result.returncode == 0 and "usage: packml " + verb in result.stdout


def test_no_running_cell_is_reported_with_exit_code_3() -> None:
    result = packml("status", "--cell", f"nothing_here_{os.getpid()}", "--timeout", "1")
    assert result.returncode == 3, result.stdout + result.stderr
    assert "no unit found" in result.stderr
