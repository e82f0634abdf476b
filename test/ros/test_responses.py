"""Service responses the middleware drops because the client is not discovered yet are sent again
(packml_ros2.responses), and node processes stop cleanly on a signal that arrives during a callback
(packml_ros2.run).

A client whose response reader can never match the service's response writer (it asks for
transient-local durability, the service offers volatile) gets its request through but never its
answer: exactly what Fast DDS does to a client whose reader the server has not discovered yet, made
permanent so that the retries can be watched."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from packml_ros2.responses import Resender
from packml_ros2.testing.processes import wait_until

ROOT = Path(__file__).resolve().parents[2]


# -- the resender on its own ------------------------------------------------------------------------
class Log:
    def __init__(self) -> None:
        self.lines: list[tuple[str, str]] = []
        self.changed = threading.Condition()

    def _add(self, level: str, text: str) -> None:
        with self.changed:
            self.lines.append((level, text))
            self.changed.notify_all()

    def info(self, text: str) -> None:
        self._add("info", text)

    def warning(self, text: str) -> None:
        self._add("warning", text)

    def error(self, text: str) -> None:
        self._add("error", text)

    def wait(self, count: int, timeout: float = 5.0) -> list[tuple[str, str]]:
        with self.changed:
            assert self.changed.wait_for(lambda: len(self.lines) >= count, timeout), self.lines
            return list(self.lines)


def test_a_lost_response_is_retried_until_sent() -> None:
    results = iter([False, False, True])
    calls: list[float] = []

    def attempt() -> bool:
        calls.append(time.monotonic())
        return next(results)

    resender, log = Resender(window=5.0, period=0.01), Log()
    resender.add("/c/u/reset", attempt, log)
    lines = log.wait(2)
    assert lines[0][0] == "warning" and "/c/u/reset not delivered" in lines[0][1]
    assert lines[1][0] == "info" and "/c/u/reset sent after" in lines[1][1]
    assert "(4 attempts)" in lines[1][1]  # the first send and three retries
    assert len(calls) == 3 and resender.sent == 1 and resender.given_up == 0


def test_a_response_never_delivered_is_given_up_after_the_window() -> None:
    attempts = []
    resender, log = Resender(window=0.2, period=0.02), Log()
    start = time.monotonic()
    resender.add("/c/u/start", lambda: attempts.append(1) and False, log)
    level, text = log.wait(2)[1]
    assert level == "error" and "/c/u/start lost" in text and "within 0.2 s" in text
    assert time.monotonic() - start >= 0.2
    assert len(attempts) >= 3 and resender.given_up == 1 and resender.sent == 0


def test_retries_of_several_responses_interleave_and_a_failing_one_is_dropped() -> None:
    resender, log = Resender(window=5.0, period=0.01), Log()
    state = {"a": 0}

    def slow() -> bool:
        state["a"] += 1
        return state["a"] >= 5

    def broken() -> bool:
        raise RuntimeError("cannot use Destroyable because destruction was requested")

    resender.add("/c/u/a", slow, log)
    resender.add("/c/u/b", broken, log)
    resender.add("/c/u/c", lambda: True, log)
    lines = log.wait(6)
    texts = [t for _, t in lines]
    assert any("/c/u/b not delivered: cannot use Destroyable" in t for t in texts)
    # c, retried once, is sent before a's fifth attempt
    done = [t.split()[2] for t in texts if "sent after" in t]
    assert done == ["/c/u/c", "/c/u/a"]


def test_a_window_of_zero_sends_once_only() -> None:
    resender, log = Resender(window=0.0), Log()
    resender.add("/c/u/stop", lambda: pytest.fail("retried"), log)
    assert log.lines == [("error", log.lines[0][1])] and "not sent again" in log.lines[0][1]


def test_a_bad_resend_window_fails_naming_the_variable(monkeypatch: pytest.MonkeyPatch) -> None:
    from packml_ros2.responses import resend_window

    monkeypatch.setenv("PACKML_RESPONSE_RESEND_S", "soon")
    with pytest.raises(ValueError, match=r"PACKML_RESPONSE_RESEND_S='soon': expected a number"):
        resend_window()
    monkeypatch.setenv("PACKML_RESPONSE_RESEND_S", "-1")
    with pytest.raises(ValueError, match="must be 0 or more"):
        resend_window()
    monkeypatch.setenv("PACKML_RESPONSE_RESEND_S", "2.5")
    assert resend_window() == 2.5


# -- a unit process and a client whose answers the middleware drops -------------------------------
def _unreachable_client(ros: Any, srv_type: Any, name: str) -> Any:
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    profile = QoSProfile(
        depth=10,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )
    return ros.node.create_client(srv_type, name, qos_profile=profile)


def _request_until_the_unit_reports_a_loss(client: Any, srv_type: Any, proc: Any, name: str) -> Any:
    """Send requests until the unit has received one (it reports the undelivered answer). The
    client's request writer is matched some time after the unit's service appeared: no API says
    when, so an unanswered request is simply sent again (at most 10 times, 1 s apart)."""
    futures = []
    for _ in range(10):
        futures.append(client.call_async(srv_type.Request()))
        try:
            wait_until(lambda: f"response of {name} not delivered" in proc.output(), 1.0)
            return futures
        except TimeoutError:
            continue
    raise AssertionError(f"the unit never reported a dropped answer:\n{proc.output()}")


@pytest.mark.ros
def test_a_unit_resends_a_dropped_answer_then_gives_up_and_still_answers_others(
    ros: Any, processes: Any, tmp_path: Path
) -> None:
    from packml_interfaces.srv import QueryAlarms

    from test.ros.cells import UnitClient, write_cell

    cell_file, cell = write_cell(tmp_path, {"filler": {}})
    proc = processes.module("unit_filler", "packml_ros2.unit_node", str(cell_file), "filler",
                            env={"PACKML_RESPONSE_RESEND_S": "1.5"})  # fmt: skip
    name = f"/{cell}/filler/query_alarms"
    UnitClient(ros, cell, "filler").ready()
    client = _unreachable_client(ros, QueryAlarms, name)
    futures = _request_until_the_unit_reports_a_loss(client, QueryAlarms, proc, name)
    wait_until(lambda: f"response of {name} lost" in proc.output(), 10.0, what="the give-up")
    out = proc.output()
    assert "reader was not discovered within 1.5 s" in out
    assert "failed to send response (timeout)" not in out  # recognised, not printed as a warning
    attempts = int(out.split(f"response of {name} lost")[1].split("(")[1].split()[0])
    assert attempts >= 5  # retried all along the window (each try waits up to 100 ms)
    assert not any(f.done() for f in futures)
    # the unit went on answering everyone else meanwhile
    assert ros.call(QueryAlarms, name).count == 0
    assert proc.running()


@pytest.mark.ros
def test_a_retry_ends_when_the_client_goes_away(ros: Any, processes: Any, tmp_path: Path) -> None:
    from std_srvs.srv import Trigger

    from test.ros.cells import UnitClient, write_cell

    cell_file, cell = write_cell(tmp_path, {"filler": {}})
    proc = processes.module("unit_filler", "packml_ros2.unit_node", str(cell_file), "filler",
                            env={"PACKML_RESPONSE_RESEND_S": "30"})  # fmt: skip
    name = f"/{cell}/filler/reset"
    unit = UnitClient(ros, cell, "filler")
    unit.ready()
    client = _unreachable_client(ros, Trigger, name)
    _request_until_the_unit_reports_a_loss(client, Trigger, proc, name)
    unit.status.wait_for(lambda m: m.state_current == 4, 5.0, "Idle")  # the reset was carried out
    ros.node.destroy_client(client)
    wait_until(lambda: f"response of {name} sent after" in proc.output(), 10.0,
               what="the retry to end once the client is gone")  # fmt: skip
    assert f"response of {name} lost" not in proc.output()


# -- Ctrl-C / SIGTERM during a callback -------------------------------------------------------------
SIGNAL_DURING_A_CALLBACK = """
import os, signal, sys
import rclpy
from rclpy.node import Node
from std_msgs.msg import String
from packml_ros2 import run

run.init(["probe"])
node = Node("signal_probe")
pub = node.create_publisher(String, "signal_probe", 10)

def tick():
    os.kill(os.getpid(), signal.{sig})
    sum(range(1000))  # the Python signal handler runs here, in the middle of the callback
    pub.publish(String(data="after the signal"))
    print("callback finished", flush=True)

node.create_timer(0.01, tick)
sys.exit(run.spin([node], on_shutdown=lambda: print("shut down", flush=True)))
"""


@pytest.mark.ros
@pytest.mark.parametrize("sig", ["SIGTERM", "SIGINT"])
def test_a_signal_during_a_callback_lets_it_finish_then_shuts_down(sig: str) -> None:
    """The node is shut down after the running callback, not under it (that gave a traceback:
    'cannot use Destroyable because destruction was requested')."""
    out = subprocess.run(
        [sys.executable, "-c", SIGNAL_DURING_A_CALLBACK.replace("{sig}", sig)],
        cwd=ROOT, capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["callback", "finished", "shut", "down"], out.stdout + out.stderr
    assert "Traceback" not in out.stderr and "Destroyable" not in out.stderr, out.stderr


SIGNAL_WHILE_STARTING = """
import os, signal, sys
from rclpy.node import Node
from packml_ros2 import run

run.init(["probe"])
os.kill(os.getpid(), signal.{sig})  # (a cell stopped as it starts: the node is not made yet)
node = Node("starting_probe")
print("made", flush=True)
code = run.spin([node], on_shutdown=lambda: print("shut down", run.shutdown_reason(), flush=True))
sys.exit(code)
"""


@pytest.mark.ros
@pytest.mark.parametrize("sig", ["SIGTERM", "SIGINT"])
def test_a_signal_while_the_nodes_are_made_ends_the_spin_at_once(sig: str) -> None:
    """Ctrl-C between run.init and run.spin (before: a KeyboardInterrupt traceback, exit 1)."""
    out = subprocess.run(
        [sys.executable, "-c", SIGNAL_WHILE_STARTING.replace("{sig}", sig)],
        cwd=ROOT, capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["made", "shut", "down", sig], out.stdout + out.stderr
    assert "Traceback" not in out.stderr, out.stderr


STUCK_TEARDOWN = """
import os, signal, sys, threading, time
from rclpy.node import Node
from packml_ros2 import run

run.init(["probe"])
node = Node("stuck_probe")
started = threading.Event()

def stuck():  # a callback that never returns: the executor's threads cannot be joined
    started.set()
    time.sleep(3600)

node.create_timer(0.01, stuck)
threading.Thread(target=lambda: (started.wait(), os.kill(os.getpid(), signal.SIGINT))).start()
sys.exit(run.spin([node], threads=2, on_shutdown=lambda: print("saved", flush=True)))
"""


@pytest.mark.ros
def test_a_teardown_that_hangs_after_the_nodes_closed_still_ends_the_process() -> None:
    """After on_shutdown (what the nodes keep is saved) the process ends within
    run.TEARDOWN_LIMIT even when the executor cannot join a thread (before: for ever, and
    ros2 launch / packml launch killed it and reported a failure)."""
    from packml_ros2.run import TEARDOWN_LIMIT

    t0 = time.monotonic()
    out = subprocess.run([sys.executable, "-c", STUCK_TEARDOWN], cwd=ROOT, capture_output=True,
                         text=True, timeout=60, check=False)  # fmt: skip
    assert out.returncode == 0 and out.stdout.split() == ["saved"], out.stdout + out.stderr
    assert "teardown did not end" in out.stderr and "Traceback" not in out.stderr, out.stderr
    assert time.monotonic() - t0 < TEARDOWN_LIMIT + 10


EXIT_STUCK = """
import os, signal, sys, threading, time
from rclpy.node import Node
from packml_ros2 import run

run.init(["probe"])
node = Node("exit_probe")

def saved():  # a thread nobody joins: the interpreter's exit waits for it, after spin returned
    print("saved", flush=True)
    threading.Thread(target=time.sleep, args=(3600,), name="never-ends").start()

threading.Timer(0.5, os.kill, (os.getpid(), signal.SIGINT)).start()
sys.exit(run.spin([node], on_shutdown=saved))
"""


@pytest.mark.ros
def test_an_exit_that_hangs_after_spin_returned_still_ends_the_process() -> None:
    """The watchdog covers the interpreter's own exit too (before: cancelled when spin returned,
    and a process stuck joining a thread ignored Ctrl-C and SIGTERM until SIGKILL); the stacks
    of every thread say where it was."""
    from packml_ros2.run import TEARDOWN_LIMIT

    t0 = time.monotonic()
    out = subprocess.run([sys.executable, "-c", EXIT_STUCK], cwd=ROOT, capture_output=True,
                         text=True, timeout=60, check=False)  # fmt: skip
    assert out.returncode == 0 and out.stdout.split() == ["saved"], out.stdout + out.stderr
    assert "teardown did not end" in out.stderr and "never-ends" not in out.stdout, out.stderr
    assert "in _shutdown" in out.stderr, out.stderr  # threading._shutdown: the main thread's stack
    assert time.monotonic() - t0 < TEARDOWN_LIMIT + 10


GIL_HELD = """
import ctypes, os, signal, sys, threading
from rclpy.node import Node
from packml_ros2 import run

class Stuck(Node):
    def destroy_node(self):  # a teardown stuck in C that holds the GIL, like rclpy's C++ does
        print("destroying", flush=True)
        libc = ctypes.PyDLL(None)  # PyDLL: the call keeps the GIL (ctypes.CDLL would release it)
        mutex = ctypes.create_string_buffer(64)  # a pthread mutex, all zeros: unlocked
        libc.pthread_mutex_lock(mutex)
        libc.pthread_mutex_lock(mutex)  # never returns, not even on a signal

run.init(["probe"])
node = Stuck("gil_probe")
threading.Timer(0.5, os.kill, (os.getpid(), signal.SIGINT)).start()
sys.exit(run.spin([node], on_shutdown=lambda: print("saved", flush=True)))
"""


GOODBYE_STUCK = GIL_HELD.replace(  # on_shutdown hangs (in C, holding the GIL) after "saved"
    'on_shutdown=lambda: print("saved", flush=True)',
    "on_shutdown=lambda: (print('saved', flush=True), node.destroy_node())",
)


@pytest.mark.ros
def test_a_goodbye_stuck_in_c_holding_the_gil_ends_with_the_stacks_and_code_1() -> None:
    """Seen in a fresh-clone run: an EM logged its goodbye (a log line is a DDS write to /rosout
    too) and hung inside on_shutdown, before a guard armed after it: the guard now runs from the
    stop on."""
    from packml_ros2.run import HELD_GIL_GRACE, TEARDOWN_LIMIT

    t0 = time.monotonic()
    out = subprocess.run([sys.executable, "-c", GOODBYE_STUCK], cwd=ROOT, capture_output=True,
                         text=True, timeout=60, check=False)  # fmt: skip
    assert out.returncode == 1 and out.stdout.split() == ["saved", "destroying"], out.stdout + out.stderr  # fmt: skip
    assert "in <lambda>" in out.stderr and "in spin" in out.stderr, out.stderr
    assert time.monotonic() - t0 < TEARDOWN_LIMIT + HELD_GIL_GRACE + 10


@pytest.mark.ros
def test_a_teardown_stuck_in_c_holding_the_gil_ends_with_the_stacks_and_code_1() -> None:
    """No Python thread runs while C code holds the GIL (nor the Python watchdog, nor a signal
    handler: the process ignored Ctrl-C and SIGTERM until ros2 launch SIGKILLed it): faulthandler's
    C thread writes every thread's stack and exits with code 1 (before: for ever)."""
    from packml_ros2.run import HELD_GIL_GRACE, TEARDOWN_LIMIT

    t0 = time.monotonic()
    out = subprocess.run([sys.executable, "-c", GIL_HELD], cwd=ROOT, capture_output=True,
                         text=True, timeout=60, check=False)  # fmt: skip
    assert out.returncode == 1 and out.stdout.split() == ["saved", "destroying"], out.stdout + out.stderr  # fmt: skip
    assert "in destroy_node" in out.stderr and "in spin" in out.stderr, out.stderr
    assert TEARDOWN_LIMIT + HELD_GIL_GRACE <= time.monotonic() - t0 < TEARDOWN_LIMIT + 20
