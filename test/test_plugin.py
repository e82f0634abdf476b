"""The pytest plugin's fixtures: a failing test shows what its nodes printed (CI keeps no
tmp_path), a passing one does not; a wait of the harness that times out says what it had matched."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from packml_ros2.testing.processes import wait_until

TEST = """
from packml_ros2.testing.processes import wait_until


def test_{name}(processes):
    node = processes.start("talker", "-c", "print('the node said {name}', flush=True)")
    wait_until(lambda: "said" in node.output(), 10, what="the node's line")
    assert {passes}
"""


def _run(tmp_path: Path, name: str, passes: bool) -> str:
    test = tmp_path / f"test_{name}.py"
    test.write_text(TEST.format(name=name, passes=passes))
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", str(test)],
        cwd=tmp_path, capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert done.returncode == (0 if passes else 1), done.stdout + done.stderr
    return done.stdout


def test_a_failing_test_shows_its_nodes_logs(tmp_path: Path) -> None:
    out = _run(tmp_path, "failing", passes=False)
    assert "--- talker (pid " in out and "the node said failing" in out


def test_a_passing_test_shows_none(tmp_path: Path) -> None:
    assert "the node said" not in _run(tmp_path, "passing", passes=True)


def test_a_wait_that_times_out_says_which_writers_the_subscription_had(ros) -> None:
    from std_msgs.msg import String

    seen = ros.subscribe(String, "/harness_probe", 10)
    with pytest.raises(TimeoutError, match=r"writers matched 0, in the graph 0"):
        seen.wait_for(lambda m: True, 0.2, "a probe")
    pub = ros.node.create_publisher(String, "/harness_probe", 10)
    wait_until(lambda: seen.matched == 1, 10, what="the writer matched")
    with pytest.raises(TimeoutError, match=r"writers matched 1, in the graph 1"):
        seen.wait_for(lambda m: m.data == "never", 0.2, "a probe")
    pub.publish(String(data="hello"))
    assert seen.wait_for(lambda m: True, 10).data == "hello"
