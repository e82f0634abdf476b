"""Issue 15: mutated cell files against every loader. In process, every validator a face runs
(units, simulated EMs, hmi:, opcua:) either accepts the file or raises ConfigError with a bounded
report, quickly; as the user runs them (unit_node, coordinator, packml launch/hmi/opcua), a file
that does not load ends the program with exit code 2 and one line per problem, never a traceback.
A plain-text secret in a mutated file never appears in any report."""

from __future__ import annotations

import subprocess
import sys
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from packml_ros2 import launcher
from packml_ros2.core import ConfigError, load_cell
from packml_ros2.hmi import hmi_settings
from packml_ros2.opcua.config import parse_opcua
from test.hostile.cellfiles import Mutation, mutations

REPO = Path(__file__).resolve().parents[2]
BASES = {
    name: (REPO / "config" / f"{name}.yaml").read_text() for name in ("demo_cell", "reference_cell")
}
SEED = 15
PER_BASE = 250  # 500 files: ~10 s on a quiet CI machine
MAX_SECONDS_PER_FILE = 1.0
SECRETS = ("plain-text-token-123", "plain-text-password")
LOADERS = {
    "unit_node": ["-m", "packml_ros2.unit_node"],
    "coordinator": ["-m", "packml_ros2.coordinator_node"],
    "packml launch": ["-m", "packml_ros2.cli.main", "launch", "--check"],
    "packml hmi": ["-m", "packml_ros2.cli.main", "hmi", "--check"],
    "packml opcua": ["-m", "packml_ros2.cli.main", "opcua", "--check"],
}


def validate(path: Path) -> str | None:
    """None when every face accepts the file, else the report (ConfigError only)."""
    try:
        plan = launcher.plan(path)
        hmi_settings(plan.cell)
        parse_opcua(plan.cell)
    except ConfigError as exc:
        return str(exc)
    return None


def check_report(report: str, path: Path, what: str) -> None:
    lines = report.splitlines()
    assert 1 <= len(lines) <= 51, f"{what}: {len(lines)} lines"
    assert len(report) < 40_000, f"{what}: {len(report)} characters"
    assert all(line.startswith(f"{path}: ") for line in lines), f"{what}: {report[:500]}"
    assert not any(secret in report for secret in SECRETS), f"{what}: a secret in {report!r}"


def test_every_validator_refuses_a_mutated_file_cleanly(tmp_path: Path) -> None:
    outcomes: Counter[str] = Counter()
    slowest = 0.0
    started = time.monotonic()
    for base, text in BASES.items():
        for i, m in enumerate(mutations(text, SEED, PER_BASE)):
            path = tmp_path / f"{base}_{i}.yaml"
            path.write_bytes(m.data)
            t = time.thread_time()  # CPU time: a loaded machine's waits are not the file's
            report = validate(path)  # anything but ConfigError fails the test here
            took = time.thread_time() - t
            slowest = max(slowest, took)
            assert took < MAX_SECONDS_PER_FILE, f"{base} #{i} ({m.name}): {took:.2f} s"
            if report is not None:
                check_report(report, path, f"{base} #{i} ({m.name})")
            outcomes["refused" if report else "accepted"] += 1
            path.unlink()
    # the mutations really are hostile: most are refused (seed 15: about 72 %)
    assert outcomes["refused"] > 0.6 * 2 * PER_BASE, outcomes
    assert time.monotonic() - started < 120, outcomes


def _refused_samples(tmp_path: Path, count: int) -> list[tuple[Path, Mutation]]:
    """``count`` files that load_cell itself refuses, of as many kinds of mutation as possible."""
    picked: list[tuple[Path, Mutation]] = []
    kinds: set[str] = set()
    for i, m in enumerate(mutations(BASES["demo_cell"], SEED + 1, 400)):
        kind = m.name.split(" ")[0].split(".")[0]
        if kind in kinds:
            continue
        path = tmp_path / f"refused_{i}.yaml"
        path.write_bytes(m.data)
        try:
            load_cell(path)
        except ConfigError:
            picked.append((path, m))
            kinds.add(kind)
            if len(picked) == count:
                break
    assert len(picked) == count, kinds
    return picked


@pytest.mark.parametrize("loader", list(LOADERS))
def test_every_loader_exits_2_with_one_line_per_problem(tmp_path: Path, loader: str) -> None:
    samples = _refused_samples(tmp_path, 4)

    def run(
        sample: tuple[Path, Mutation],
    ) -> tuple[Path, Mutation, subprocess.CompletedProcess[str]]:
        path, m = sample
        argv = [sys.executable, *LOADERS[loader], str(path)]
        if loader.startswith("packml"):  # (the option after the file, as a user types it)
            argv = [sys.executable, *LOADERS[loader][:-1], str(path), LOADERS[loader][-1]]
        return path, m, subprocess.run(argv, capture_output=True, text=True, timeout=60,
                                       check=False)  # fmt: skip

    with ThreadPoolExecutor(2) as pool:
        results = list(pool.map(run, samples))
    for path, m, result in results:
        what = f"{loader} on {m.name}"
        assert result.returncode == 2, f"{what}: exit {result.returncode}\n{result.stderr}"
        assert "Traceback" not in result.stderr + result.stdout, f"{what}:\n{result.stderr}"
        lines = result.stderr.strip().splitlines()
        assert lines and all(line.startswith(f"{loader}: {path}: ") for line in lines), (
            f"{what}:\n{result.stderr}"
        )
        check_report("\n".join(line.split(": ", 1)[1] for line in lines), path, what)


def _run(argv: list[str], timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, *argv], capture_output=True, text=True,
                          timeout=timeout, check=False)  # fmt: skip


def _argv(loader: str, path: Path) -> list[str]:
    if loader.startswith("packml"):
        return [*LOADERS[loader][:-1], str(path), LOADERS[loader][-1]]
    return [*LOADERS[loader], str(path)]


@pytest.mark.parametrize("loader", list(LOADERS))
def test_a_name_ros_cannot_take_is_refused_at_load_by_every_loader(tmp_path: Path, loader: str) -> None:  # fmt: skip
    """Issue 25 item 12: a cell named ``zellü`` passed ``--check``, then every node died with a
    traceback (rcl takes ASCII names only)."""
    path = tmp_path / "cell.yaml"
    path.write_text("cell: zellü\nunits:\n  fillör: {}\n", encoding="utf-8")
    result = _run(_argv(loader, path))
    assert result.returncode == 2, result
    assert "Traceback" not in result.stderr + result.stdout, result.stderr
    assert f"{path}: cell: 'zellü' is not a valid ROS name (ASCII letters" in result.stderr, result.stderr  # fmt: skip
    assert f"{path}: units.fillör: 'fillör' is not a valid ROS name" in result.stderr, result.stderr  # fmt: skip


def test_a_fifo_as_cell_token_or_users_file_is_refused_at_once(tmp_path: Path) -> None:
    """Issue 25 item 12: a named pipe as the cell file, the token file or the users file hung
    every loader in ``open`` (nobody writes to it)."""
    import os

    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    cell = tmp_path / "cell.yaml"
    started = time.monotonic()
    for loader in ("unit_node", "packml launch", "packml hmi"):
        result = _run(_argv(loader, fifo), timeout=30)
        assert result.returncode == 2 and "Traceback" not in result.stderr, result
        assert f"{fifo}: <top>: cannot read: not a regular file: a named pipe (FIFO)" in result.stderr, result.stderr  # fmt: skip
    cell.write_text("cell: c\nunits: {u: {}}\nhmi: {token: file:pipe}\n")
    result = _run(["-m", "packml_ros2.cli.main", "hmi", str(cell), "--check"], timeout=30)
    assert result.returncode == 2 and "hmi.token: cannot read" in result.stderr, result
    assert "not a regular file: a named pipe (FIFO)" in result.stderr, result.stderr
    cell.write_text("cell: c\nunits: {u: {}}\nhmi: {users_file: pipe}\n")
    result = _run(["-m", "packml_ros2.cli.main", "hmi", str(cell), "--check"], timeout=30)
    assert result.returncode == 2 and "not a regular file: a named pipe (FIFO)" in result.stderr, result  # fmt: skip
    assert time.monotonic() - started < 60


def test_an_hmi_open_to_every_machine_without_logins_is_a_warning_at_check(tmp_path: Path) -> None:
    """Issue 25 item 12: ``hmi.host: 0.0.0.0`` with neither logins nor a token passed ``--check``
    without a word (the server warned only once it served)."""
    import os

    cell = tmp_path / "cell.yaml"
    cell.write_text("cell: c\nunits: {u: {}}\nhmi: {host: 0.0.0.0}\n")
    env = {k: v for k, v in os.environ.items() if k != "PACKML_HMI_TOKEN"}
    for verb in (["hmi", str(cell), "--check"], ["launch", str(cell), "--hmi", "--check"]):
        result = subprocess.run([sys.executable, "-m", "packml_ros2.cli.main", *verb], env=env,
                                capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
        assert result.returncode == 0, result
        assert "warning" in result.stderr and "serving on 0.0.0.0 without logins or a token" in result.stderr, result  # fmt: skip
    cell.write_text("cell: c\nunits: {u: {}}\nhmi: {host: 127.0.0.1}\n")
    result = subprocess.run([sys.executable, "-m", "packml_ros2.cli.main", "hmi", str(cell), "--check"],
                            env=env, capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
    assert result.returncode == 0 and "warning" not in result.stderr, result
