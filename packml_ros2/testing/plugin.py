"""pytest plugin ``packml_ros2`` (loaded automatically where packml_ros2 is installed).

At start it makes the test process (and every child) localhost-only with quick discovery and a
ROS domain of its own (per run and per pytest-xdist worker). Fixtures:

- ``ros_domain``: the domain of this worker;
- ``ros``: a :class:`~packml_ros2.testing.harness.RosHarness` on a fresh Context;
- ``processes``: start nodes as separate OS processes; stopped (SIGINT) at teardown;
- ``packml_replay``: replay-check a recorded bag, e.g.
  ``packml_replay("test/bags/normal_production").assert_matches()`` (packml_ros2.testing.replay).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Generator, Iterator
from pathlib import Path

import pytest

from .environment import allocate_domain, localhost_environment


def pytest_configure(config: pytest.Config) -> None:
    localhost_environment()
    os.environ.setdefault("ROS_PYTHON_CHECK_FIELDS", "1")
    # Every process (each pytest-xdist worker too) locks a domain of its own; children inherit it.
    os.environ["ROS_DOMAIN_ID"] = str(allocate_domain())


@pytest.fixture(scope="session")
def ros_domain() -> int:
    return int(os.environ["ROS_DOMAIN_ID"])


@pytest.fixture
def ros(ros_domain: int) -> Iterator[object]:
    from .harness import RosHarness

    harness = RosHarness(ros_domain)
    try:
        yield harness
    finally:
        harness.close()


@pytest.hookimpl(wrapper=True, tryfirst=True)
def pytest_runtest_makereport(
    item: pytest.Item, call: pytest.CallInfo[None]
) -> Generator[None, pytest.TestReport, pytest.TestReport]:
    """Keep each phase's report on the item: the ``processes`` fixture reads whether the test
    failed."""
    report = yield
    setattr(item, f"packml_report_{call.when}", report)
    return report


#: characters of each process's log printed when a test fails (its last ones)
LOG_TAIL = 4000


@pytest.fixture
def processes(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[object]:
    from .processes import Processes

    log_dir = tmp_path / "logs"
    log_dir.mkdir(exist_ok=True)
    procs = Processes(log_dir)
    try:
        yield procs
    finally:
        report = getattr(request.node, "packml_report_call", None)
        if report is not None and report.failed:
            # what the nodes said is what a failure in CI needs (tmp_path is gone by then)
            for proc in procs.started:
                print(f"--- {proc.name} (pid {proc.pid}) log, last {LOG_TAIL} characters ---")
                print(proc.output()[-LOG_TAIL:])
        failures = procs.close()
        if failures:
            print(failures)


@pytest.fixture
def packml_replay(request: pytest.FixtureRequest) -> Callable[..., object]:
    """``packml_replay(bag, config=None, units=()) -> ReplayResult`` (paths relative to the
    pytest root directory); ``.assert_matches()`` fails with the first difference."""
    from .replay import BagReplayer

    return BagReplayer(request.config.rootpath)
