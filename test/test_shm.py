"""packml_ros2.testing.shm: a Fast DDS file a live process holds is never removed, also when
that process closes another file while it is being looked at, and nothing is removed when a live
process can only be read in part. (Before: an fd closed during the scan ended the scan of its process, its
later files counted as stale and were deleted: a live participant's port lock, which the next
participant to start then took over, so nobody heard it.)"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from packml_ros2.testing import shm


@pytest.fixture
def held() -> Iterator[tuple[Path, int]]:
    path = Path(f"/dev/shm/fastdds_packml_test_{os.getpid()}")
    path.write_bytes(b"x")
    fd = os.open(path, os.O_RDONLY)
    try:
        yield path, fd
    finally:
        os.close(fd)
        path.unlink(missing_ok=True)


def test_a_file_held_open_survives_an_fd_closed_during_the_scan(
    held: tuple[Path, int], monkeypatch: pytest.MonkeyPatch
) -> None:
    path, fd = held
    real = os.readlink

    def readlink(link: os.PathLike[str] | str) -> str:
        name = Path(link)
        if (
            name.parent.name == "fd"
            and name.parent.parent.name == str(os.getpid())
            and int(name.name) < fd
        ):
            raise FileNotFoundError(link)  # every earlier fd of ours "closed" meanwhile
        return real(link)

    monkeypatch.setattr(shm.os, "readlink", readlink)
    assert path not in shm.stale_files()
    assert shm.cleanup() >= 0 and path.exists()


def test_nothing_is_removed_when_a_live_process_is_read_in_part(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    stale = Path(f"/dev/shm/fastdds_packml_stale_{os.getpid()}")
    stale.write_bytes(b"x")
    try:
        assert stale in shm.stale_files(min_age=0)  # held by nobody
        real = os.readlink

        def readlink(link: os.PathLike[str] | str) -> str:
            if Path(link).parent.parent.name == str(os.getpid()):
                raise OSError(5, "Input/output error", str(link))  # a process half read
            return real(link)

        monkeypatch.setattr(shm.os, "readlink", readlink)
        assert shm.stale_files(min_age=0) == [] and shm.cleanup() == 0 and stale.exists()
    finally:
        stale.unlink(missing_ok=True)


def test_a_file_made_while_the_processes_are_scanned_is_never_removed(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A participant that starts during the scan makes its port files after its process was
    looked at: they are not candidates (listed before the scan), and a file nobody holds yet is
    young anyway. (Before: its port files were deleted and it stayed deaf to every writer that
    had sent to that port: 5 readers of 12 started under a cleanup loop, 0 since.)"""
    born = Path(f"/dev/shm/fastdds_packml_born_{os.getpid()}")
    real = shm._in_use

    def scan() -> set[str]:
        born.write_bytes(b"x")  # made by a process the scan has passed
        return real()

    monkeypatch.setattr(shm, "_in_use", scan)
    try:
        assert born not in shm.stale_files(min_age=0)
        monkeypatch.setattr(shm, "_in_use", real)
        assert born.exists() and born not in shm.stale_files()  # held by nobody, but young
        assert born in shm.stale_files(min_age=0)
    finally:
        born.unlink(missing_ok=True)


def test_a_live_ports_mutex_stays_while_its_port_lives() -> None:
    """Fast DDS holds a port's named mutex (``sem.fastdds_port<N>_mutex``) neither open nor
    mapped between uses: it is removed with its port only, never under a live one."""
    port = Path(f"/dev/shm/fastdds_port_packml_{os.getpid()}")
    mutex = port.with_name(f"sem.{port.name}_mutex")
    port.write_bytes(b"x")
    mutex.write_bytes(b"x")
    fd = os.open(port, os.O_RDONLY)  # the port's listener
    try:
        stale = shm.stale_files(min_age=0)
        assert port not in stale and mutex not in stale
        os.close(fd)
        fd = -1
        stale = shm.stale_files(min_age=0)  # the port is free: both go
        assert port in stale and mutex in stale
        port.unlink()
        assert mutex in shm.stale_files(min_age=0)  # a mutex whose port is gone is stale
    finally:
        if fd >= 0:
            os.close(fd)
        port.unlink(missing_ok=True)
        mutex.unlink(missing_ok=True)
