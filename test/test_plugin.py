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


def test_a_latched_subscription_deaf_half_way_through_a_wait_is_replaced(ros) -> None:
    """A first reader that drops everything (as the deaf reader seen in CI): half way through
    the wait, with the writer on the graph, the harness subscribes again and the new reader
    takes the latched sample; the old one is gone, so nothing arrives twice."""
    from rclpy.qos import DurabilityPolicy, QoSProfile
    from std_msgs.msg import String

    latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    pub = ros.node.create_publisher(String, "/harness_latched", latched)
    pub.publish(String(data="latched"))
    real = ros.node.create_subscription
    calls: list[str] = []

    def deaf_first(msg_type, topic, callback, *args, **kwargs):  # type: ignore[no-untyped-def]
        calls.append(topic)
        return real(msg_type, topic, callback if len(calls) > 1 else (lambda m: None), *args,
                    **kwargs)  # fmt: skip

    ros.node.create_subscription = deaf_first
    try:
        seen = ros.subscribe(String, "/harness_latched", latched)
        assert seen.wait_for(lambda m: True, 6, "the latched sample").data == "latched"
    finally:
        del ros.node.create_subscription
    assert seen.resubscribed and calls == ["/harness_latched"] * 2
    pub.publish(String(data="next"))
    assert seen.wait_for(lambda m: m.data == "next", 10).data == "next"
    assert [m.data for m in seen.messages] == ["latched", "next"]  # the deaf one was destroyed
    # a volatile subscription is never replaced: a message it missed is not sent again
    plain = ros.subscribe(String, "/harness_plain", 10)
    ros.node.create_publisher(String, "/harness_plain", 10)
    with pytest.raises(TimeoutError):
        plain.wait_for(lambda m: True, 0.4)
    assert not plain.resubscribed
