"""Suite-wide: the packml_ros2 pytest plugin (installed with the package) already made every
process localhost-only with its own ROS domain. Here: a watch on the machine's network interfaces
for the whole run — a DDS (RTPS) packet leaving the machine fails the suite."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from test.netwatch import RtpsWatch


@pytest.fixture(scope="session", autouse=True)
def no_dds_leaves_the_machine(request: pytest.FixtureRequest) -> Iterator[RtpsWatch | None]:
    watch = RtpsWatch.on_external_interfaces()
    if watch is None:
        yield None
        return
    watch.start()
    yield watch
    watch.stop()
    if watch.packets:
        request.session.shouldfail = f"{len(watch.packets)} DDS packet(s) left the machine during the suite: {watch.packets[:3]}"


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    if isinstance(session.shouldfail, str) and "DDS packet" in session.shouldfail:
        print(f"\nFAILED: {session.shouldfail}")
        session.exitstatus = pytest.ExitCode.TESTS_FAILED
