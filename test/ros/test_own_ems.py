"""Issue 26: the integrator's own EMs in a launched cell. How each EM runs is in the cell file
(``sim:``, ``run:``, ``external:``); ``packml launch --check`` lists it and refuses a wrong entry
naming its key; one cell mixing a simulated EM, a Python EM from ``run:`` and an external EM
started by hand runs reset, start, hold, unhold, stop and abort under ``packml launch`` and
``packml launch --processes`` (ros2 launch: test/workspace/test_launch.py)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml

from packml_ros2.testing.processes import kill_environ_holders

from .test_launcher_cli import FAST, Launched
from .test_multihost import Network, _ns_environment, network  # noqa: F401 (a fixture)

PACKML = [sys.executable, "-m", "packml_ros2.cli.main"]

#: The integrator's EMs: each hook appends "<em> <hook>" to $EMS_TRACE (the test reads it back:
#: the real code ran, not a simulator). ``camera.py`` is the external EM, started by hand.
EMS = textwrap.dedent(
    """
    import asyncio, os, sys
    from packml_ros2 import run
    from packml_ros2.equipment_module import EquipmentModule, StateContext

    class Traced(EquipmentModule):
        def trace(self, what: str) -> None:
            with open(os.environ["EMS_TRACE"], "a") as f:
                f.write(f"{self.em_name} {what}\\n")

        async def on_resetting(self, ctx: StateContext) -> None:
            self.trace("resetting")

        async def on_starting(self, ctx: StateContext) -> None:
            self.trace("starting")

        async def on_holding(self, ctx: StateContext) -> None:
            self.trace("holding")

        async def on_stopping(self, ctx: StateContext) -> None:
            self.trace("stopping")

        async def on_aborting(self, ctx: StateContext) -> None:
            self.trace("aborting")

    class Gripper(Traced):
        async def execute(self, ctx: StateContext) -> None:
            while True:
                await ctx.finish(asyncio.sleep(0.2))
                self.count("processed")

    class NotAnEm:
        pass

    def main() -> int:
        run.init()
        cam = Traced(os.environ.get("PACKML_EM", "camera"), "press", sys.argv[1])
        return run.spin([cam], on_shutdown=cam.close)

    if __name__ == "__main__":
        sys.exit(main())
    """
)


def write_cell(tmp_path: Path, cell: str, ems: dict[str, object]) -> Path:
    (tmp_path / "my_ems.py").write_text(EMS)
    doc = {"cell": cell, "units": {"press": {"persistence": False, "equipment_modules": ems}}}
    path = tmp_path / f"{cell}.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def env_for(tmp_path: Path, base: dict[str, str] | None = None) -> dict[str, str]:
    """``base`` (default: this process's) with the EMs' module importable and their trace file."""
    env = dict(os.environ if base is None else base)
    path = os.pathsep.join(p for p in (str(tmp_path), env.get("PYTHONPATH", "")) if p)
    return dict(env, PYTHONPATH=path, EMS_TRACE=str(tmp_path / "trace.txt"), PYTHONUNBUFFERED="1")


@dataclass(frozen=True)
class Host:
    """Where the test's commands run: here, or in a network namespace (prefix, environment)."""

    prefix: tuple[str, ...] = ()
    env: dict[str, str] | None = None


HERE = Host()


def packml(tmp_path: Path, *args: str, host: Host = HERE,
           timeout: float = 120.0) -> subprocess.CompletedProcess[str]:  # fmt: skip
    return subprocess.run([*host.prefix, *PACKML, *args], check=False, capture_output=True,
                          text=True, timeout=timeout, env=env_for(tmp_path, host.env))  # fmt: skip


MIXED = {
    "feeder": {"sim": {"durations": FAST, "cycle_time": 0.2}},
    "gripper": {"run": "my_ems:Gripper"},
    "camera": {"external": {"timeout": 120}},
}


# -- --check ----------------------------------------------------------------------------------------------
def test_check_lists_how_every_em_runs(tmp_path: Path) -> None:
    path = write_cell(tmp_path, "chk", {
        **MIXED,
        "arm": {"run": "my_ems:Gripper", "process": "controller"},
        "wrist": {"run": "my_ems:Gripper", "process": "controller"},
        "scanner": {"run": ["my_ems:main", "{cell}"]},
        "conveyor": {"run": f"{sys.executable} -c pass {{unit}}"},
    })  # fmt: skip
    result = packml(tmp_path, "launch", "--check", str(path))
    assert result.returncode == 0, result.stderr
    lines = {line.split()[0]: line for line in result.stdout.splitlines()[2:]}
    assert "sim: simulated" in lines["press/feeder"]
    assert "run: my_ems:Gripper" in lines["press/gripper"]
    assert "external: started elsewhere; waited for 120 s" in lines["press/camera"]
    assert (
        "in process 'controller'" in lines["press/arm"] and "'controller'" in lines["press/wrist"]
    )
    assert "run: program" in lines["press/scanner"] and "chk" in lines["press/scanner"]
    assert "-c pass press" in lines["press/conveyor"]
    # --sim: a dry run of the same file, every EM simulated
    dry = packml(tmp_path, "launch", "--check", "--sim", str(path))
    assert dry.returncode == 0, dry.stderr
    ems = dry.stdout.splitlines()[2:]
    assert len(ems) == 7 and all("sim: simulated" in line for line in ems), dry.stdout


BAD = [
    ({}, "units.press.equipment_modules.e", "says not how it runs: give one of sim:, run:"),
    ({"run": "nowhere_module:X"}, "units.press.equipment_modules.e.run",
     "module 'nowhere_module' cannot be imported: ModuleNotFoundError"),
    ({"run": "my_ems:Nothing"}, "units.press.equipment_modules.e.run", "module 'my_ems' has no 'Nothing'"),
    ({"run": "my_ems:NotAnEm"}, "units.press.equipment_modules.e.run",
     "my_ems:NotAnEm is a class but not an EquipmentModule"),
    ({"run": "no-such-program --x"}, "units.press.equipment_modules.e.run",
     "executable 'no-such-program' not found"),
    ({"run": "my_ems:Gripper", "sim": {}}, "units.press.equipment_modules.e",
     "both sim and run given: an EM runs one way only"),
    ({"external": False}, "units.press.equipment_modules.e.external", "expected true"),
    ({"external": {"timeout": -1}}, "units.press.equipment_modules.e.external.timeout",
     "expected seconds > 0"),
    ({"external": True, "process": "x"}, "units.press.equipment_modules.e.process", "no process"),
    ({"run": "ls {nope}"}, "units.press.equipment_modules.e.run", "unknown placeholder"),
    ({"run": "my_ems:Gripper --x"}, "units.press.equipment_modules.e.run", "takes no arguments"),
    ({"runn": "my_ems:Gripper"}, "units.press.equipment_modules.e.runn", "did you mean 'run'?"),
]  # fmt: skip


@pytest.mark.parametrize(("entry", "path", "sentence"), BAD, ids=[str(b[0]) for b in BAD])
def test_a_wrong_entry_is_refused_at_check_with_its_key_path(
    tmp_path: Path, entry: dict[str, object], path: str, sentence: str
) -> None:
    cell = write_cell(tmp_path, "bad", {"e": entry})
    result = packml(tmp_path, "launch", "--check", str(cell))
    assert result.returncode == 2, result.stdout + result.stderr
    assert f"{path}: " in result.stderr and sentence in result.stderr, result.stderr
    assert "Traceback" not in result.stderr


# -- the mixed cell, launched --------------------------------------------------------------------------------
class Camera:
    """The external EM, started by hand in a process of its own (``prefix``: e.g. ip netns exec)."""

    def __init__(self, tmp_path: Path, cell: str, host: Host = HERE) -> None:
        self.log = (tmp_path / "camera.log").open("wb")
        argv = [*host.prefix, sys.executable, str(tmp_path / "my_ems.py"), cell]
        self.proc = subprocess.Popen(argv, stdout=self.log, stderr=subprocess.STDOUT,
                                     env=env_for(tmp_path, host.env))  # fmt: skip

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.log.close()


class LaunchedHere(Launched):
    def __init__(self, args: list[str], tmp_path: Path, host: Host = HERE) -> None:
        self.log = tmp_path / "launch.log"
        self._out = self.log.open("wb")
        self.proc = subprocess.Popen([*host.prefix, *PACKML, "launch", *args], stdout=self._out,
                                     stderr=subprocess.STDOUT, env=env_for(tmp_path, host.env))  # fmt: skip

    def wait_text(self, text: str, timeout: float = 60.0) -> None:
        deadline = time.monotonic() + timeout
        while text not in self.output():
            assert self.proc.poll() is None, f"packml launch exited:\n{self.output()}"
            assert time.monotonic() < deadline, f"{text!r} not seen:\n{self.output()}"
            time.sleep(0.05)


def traced(tmp_path: Path) -> list[str]:
    trace = tmp_path / "trace.txt"
    return trace.read_text().splitlines() if trace.exists() else []


def run_through_the_states(tmp_path: Path, host: Host = HERE) -> None:
    """reset, start, hold, unhold, stop, reset, start, abort: each settles in its wait state,
    and the gripper's and the camera's own hooks ran for each."""
    steps = [("reset", "IDLE"), ("start", "EXECUTE"), ("hold", "HELD"), ("unhold", "EXECUTE"),
             ("stop", "STOPPED"), ("reset", "IDLE"), ("start", "EXECUTE"), ("abort", "ABORTED")]  # fmt: skip
    for command, state in steps:
        result = packml(tmp_path, "cmd", "press", command, host=host)
        assert result.returncode == 0, result.stdout + result.stderr
        assert f"now {state}" in result.stdout, result.stdout
    lines = traced(tmp_path)
    for em in ("gripper", "camera"):
        hooks = [line.split()[1] for line in lines if line.split()[0] == em]
        assert hooks == ["resetting", "starting", "holding", "stopping", "resetting", "starting",
                         "aborting"], (em, lines)  # fmt: skip


@pytest.fixture
def cleanup(tmp_path: Path) -> Iterator[list[object]]:
    started: list[object] = []
    yield started
    for thing in reversed(started):
        if isinstance(thing, Camera | Servers):
            thing.stop()
        elif isinstance(thing, Launched) and thing.proc.poll() is None:
            thing.proc.send_signal(signal.SIGINT)  # the launcher stops what it started
            try:
                thing.proc.wait(20)
            except subprocess.TimeoutExpired:
                thing.proc.kill()
                thing.proc.wait()
    # whatever is left of a failed test (its nodes are in sessions of their own): a node left
    # running would be a second unit 'press' in the next test's domain
    kill_environ_holders(f"EMS_TRACE={tmp_path / 'trace.txt'}")


#: the camera as a program the launcher starts (run: a function, with a placeholder argument)
PROGRAM = {**MIXED, "camera": {"run": ["my_ems:main", "{cell}"]}}

#: an EM made of an existing ROS 2 action server (no code: interface_em), beside the others
SERVERS = Path(__file__).with_name("fake_servers.py")
MOVER = {"action": {"type": "test_msgs/action/Fibonacci", "name": "move", "timeout": 10,
                    "alarm": {"id": 5001, "category": 2},
                    "states": {"starting": {"goal": {"order": 2}},
                               "execute": {"goal": {"order": 2}, "repeat": True}}}}  # fmt: skip
WITH_ACTION = {**MIXED, "mover": MOVER}


class Servers:
    """The robot's existing drivers (an action server and a service) in a process of their own."""

    def __init__(self, tmp_path: Path, cell: str, host: Host = HERE) -> None:
        self.log_path = tmp_path / "servers.log"
        self.log = self.log_path.open("wb")
        base = f"/{cell}/press"
        argv = [*host.prefix, sys.executable, str(SERVERS), f"{base}/move", f"{base}/grip", "0.05"]
        self.proc = subprocess.Popen(argv, stdout=self.log, stderr=subprocess.STDOUT,
                                     env=env_for(tmp_path, host.env))  # fmt: skip
        deadline = time.monotonic() + 60
        while "drivers ready" not in self.output():
            assert self.proc.poll() is None and time.monotonic() < deadline, self.output()
            time.sleep(0.05)

    def output(self) -> str:
        return self.log_path.read_text(errors="replace")

    def stop(self) -> None:
        Camera.stop(self)  # type: ignore[arg-type]


@pytest.mark.timeout(300)  # eight packml cmd processes
@pytest.mark.parametrize(
    ("processes", "ems"),
    [(False, MIXED), (True, MIXED), (False, PROGRAM), (False, WITH_ACTION), (True, WITH_ACTION)],
    ids=["one-process", "processes", "program", "action-one-process", "action-processes"],
)
def test_a_cell_of_sim_run_and_external_ems(
    tmp_path: Path, cleanup: list[object], processes: bool, ems: dict[str, object]
) -> None:
    cell = f"own{os.getpid()}{int(processes)}{len(str(ems))}"
    path = write_cell(tmp_path, cell, ems)
    servers = None
    if "mover" in ems:
        servers = Servers(tmp_path, cell)
        cleanup.append(servers)
    args = ["--processes", str(path)] if processes else [str(path)]
    launch = LaunchedHere(args, tmp_path)
    cleanup.append(launch)
    if "external" in ems["camera"]:  # type: ignore[operator]
        launch.wait_text("waiting for external EM(s) press/camera")
        assert "is up" not in launch.output()
        cleanup.append(Camera(tmp_path, cell))
    launch.wait_ready()
    if processes:  # the unit, the feeder, the gripper, (the mover,) the coordinator
        assert f"{4 + (servers is not None)} processes" in launch.output()
    run_through_the_states(tmp_path)
    if servers is not None:  # the mover's goals: Starting's twice, and Execute's
        assert servers.output().count("goal 2 succeeded") >= 3, servers.output()
    assert launch.ctrl_c() == 0, launch.output()[-3000:]


@pytest.mark.timeout(300)
def test_an_external_em_that_never_comes_is_given_up_with_a_message(
    tmp_path: Path, cleanup: list[object]
) -> None:
    cell = f"late{os.getpid()}"
    path = write_cell(tmp_path, cell, {"gripper": {"run": "my_ems:Gripper"},
                                       "camera": {"external": {"timeout": 2}}})  # fmt: skip
    launch = LaunchedHere([str(path)], tmp_path)
    cleanup.append(launch)
    launch.wait_text("not answering: EM press/camera (external, not online after 2 s: start it")
    assert launch.proc.poll() is None  # the cell stays up: the camera may still come
    refused = packml(tmp_path, "cmd", "press", "reset")
    assert refused.returncode == 1 and "camera" in refused.stdout + refused.stderr
    cleanup.append(Camera(tmp_path, cell))
    deadline = time.monotonic() + 30
    while packml(tmp_path, "cmd", "press", "reset").returncode != 0:
        assert time.monotonic() < deadline, "the camera never joined"
    assert launch.ctrl_c() == 0, launch.output()[-3000:]


@pytest.mark.netns
@pytest.mark.timeout(300)
def test_the_external_em_on_another_host(
    network: Network,  # noqa: F811 (the fixture of test_multihost)
    tmp_path: Path,
    cleanup: list[object],
) -> None:
    """The cell launched on host "units", the camera started by hand on host "ems" (network
    namespaces joined by a bridge: the robot's own PC)."""
    units = Host(tuple(network.exec_args("units")), _ns_environment())
    ems = Host(tuple(network.exec_args("ems")), _ns_environment())
    cell = f"nsown{os.getpid()}"
    path = write_cell(tmp_path, cell, MIXED)
    launch = LaunchedHere([str(path)], tmp_path, units)
    cleanup.append(launch)
    launch.wait_text("waiting for external EM(s) press/camera")
    cleanup.append(Camera(tmp_path, cell, ems))
    launch.wait_ready()
    run_through_the_states(tmp_path, units)
    assert launch.ctrl_c() == 0, launch.output()[-3000:]
