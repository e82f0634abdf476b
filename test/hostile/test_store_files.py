"""Issue 15: corrupted stores. Every store on disk the product opens, damaged as a full disk, a
crash, another program or an attacker leaves it: a unit's admin store (SQLite snapshot, journal,
lock: core.persistence), a line's store (SQLite: core.line.store) and the self-signed OPC UA
certificate (opcua.server.own_certificate). Seeded and bounded: every
mutation by name, then random bit flips, byte runs and truncations.

For each: the unit (the line) starts, or refuses with one line naming the file and why (a
directory or a device where the file should be); never another exception. A store that starts
with a problem has moved the bad file aside (``<file>.unreadable-<time>``), says so in a sentence
(the unit also raises its ``store_unreadable`` alarm), works (commands, queries, writes) and opens
cleanly the next time. Memory stays bounded whatever the file holds (a huge row, ``/dev/zero``).
As the user runs them, unit_node and the coordinator log the problem, or exit 2 with one line."""

from __future__ import annotations

import os
import random
import shutil
import sqlite3
import subprocess
import sys
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

from packml_ros2.core import Cmd, Store, StoreError, Unit
from packml_ros2.core import persistence as persistence_module
from packml_ros2.core.line.store import LineStore
from packml_ros2.testing.processes import NodeProcess
from test.core.helpers import FakeClock, cell_unit
from test.core.line_sim import NS, SimLine
from test.core.test_line_scenarios import cell_doc, started

SEED = 15
RANDOM_PER_STORE = 40
PEAK_BYTES = 8 * 2**20  # Python memory while opening: a store's limits are 16 MB / 1 MB texts
HUGE = 40 * 2**20  # a row larger than any limit
UNIT = {
    "alarms": [{"id": 42, "message": "guard door", "category": 3}],
    "counters": {"processed": [{"id": 1, "name": "cartons"}]},
    "remote_commands_enabled": True,
}
STORE_UNREADABLE = 9004
Mutate = Callable[[Path, random.Random], None]


# -- the stores, as a used unit and line leave them -------------------------------------------------
def used_unit_store(path: Path) -> None:
    unit = Unit(cell_unit(UNIT), FakeClock(5_000.0), Store(path, "u"))
    unit.command(Cmd.RESET)
    unit.command(Cmd.START)
    unit.em_count("em", "processed", 0, 7)
    unit.set_alarm(42)
    unit.close()
    # the journal's records after the snapshot: a second life without a close
    again = Store(path, "u")
    again.append([{"set": {"mach_speed": 12.5}}])
    again.close()


def used_line_store(path: Path) -> None:
    sim = started(cell_doc(), str(path))
    sim.run_until(12)
    sim.line.close()


# -- mutations ----------------------------------------------------------------------------------------
def truncated(p: Path, rng: random.Random) -> None:
    data = p.read_bytes()
    p.write_bytes(data[: rng.randrange(len(data))])


def bit_flips(p: Path, rng: random.Random) -> None:
    data = bytearray(p.read_bytes())
    for _ in range(rng.choice((1, 3, 30))):
        data[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
    p.write_bytes(bytes(data))


def byte_run(p: Path, rng: random.Random) -> None:
    data = bytearray(p.read_bytes())
    at = rng.randrange(len(data))
    data[at : at + rng.randrange(1, 600)] = rng.randbytes(rng.randrange(1, 600))
    p.write_bytes(bytes(data))


def zero_length(p: Path, rng: random.Random) -> None:
    p.write_bytes(b"")


def garbage(p: Path, rng: random.Random) -> None:
    p.write_bytes(rng.randbytes(rng.randrange(1, 9000)))


def directory(p: Path, rng: random.Random) -> None:
    p.unlink()
    p.mkdir()


def dev_zero(p: Path, rng: random.Random) -> None:
    p.unlink()
    p.symlink_to("/dev/zero")


def sql(*statements: str, args: tuple[Any, ...] = ()) -> Mutate:
    def mutate(p: Path, rng: random.Random) -> None:
        db = sqlite3.connect(p)
        for s in statements:
            db.execute(s, args if "?" in s else ())
        db.commit()
        db.close()

    return mutate


def journal(mutate: Mutate) -> Mutate:
    """``mutate`` applied to the unit's journal (``<store>.journal``) instead."""

    def on_journal(p: Path, rng: random.Random) -> None:
        j = p.with_name(p.name + ".journal")
        if not j.exists():
            j.write_bytes(b"")
        mutate(j, rng)

    return on_journal


def journal_line(text: str) -> Mutate:
    """A journal line with a good checksum (what a bug or an attacker writes)."""

    def append(p: Path, rng: random.Random) -> None:
        import zlib

        with p.with_name(p.name + ".journal").open("ab") as f:
            f.write(f"{zlib.crc32(text.encode()):08x} ".encode() + text.encode() + b"\n")

    return append


FILE: dict[str, Mutate] = {
    "truncated": truncated,
    "bit flips": bit_flips,
    "byte run": byte_run,
    "zero length": zero_length,
    "garbage": garbage,
    "a directory": directory,
    "a symlink to /dev/zero": dev_zero,
}
DOC = "UPDATE unit_admin SET document = "
UNIT_MUTATIONS: dict[str, Mutate] = {
    **FILE,
    "another schema version": sql("UPDATE unit_admin SET schema = 2"),
    "schema of another type": sql("UPDATE unit_admin SET schema = 'one'"),
    "document an integer": sql(DOC + "5"),
    "document a blob": sql(DOC + "x'00ff10'"),
    "document a list": sql(DOC + "'[1, 2]'"),
    "document null": sql(DOC + "'null'"),
    "document not UTF-8": sql(DOC + "CAST(x'7b22ff223a317d' AS TEXT)"),
    "document NaN speed": sql(
        DOC + 'replace(document, \'"mach_speed":\', \'"mach_speed":NaN,"x":\')'
    ),
    "document 1e999": sql(
        DOC + 'replace(document, \'"mach_speed":\', \'"mach_speed":1e999,"x":\')'
    ),
    "a count past int32": sql(
        DOC + "json_set(document, '$.counters.processed', json('[[3000000000, 1]]'))"
    ),
    "a sequence past uint32": sql(DOC + "json_set(document, '$.sequence', 5000000000)"),
    "an alarm id past int32": sql(DOC + "json_set(document, '$.alarms.history[0].id', 9999999999)"),
    "a huge row": sql(DOC + "?", args=('{"x": "' + "a" * HUGE + '"}',)),
    "another program's table": sql("CREATE TABLE other (x)"),
    "a dropped table": sql("DROP TABLE unit_admin"),
    "journal: bit flips": journal(bit_flips),
    "journal: garbage": journal(garbage),
    "journal: a directory": journal(directory),
    "journal: a symlink to /dev/zero": journal(dev_zero),
    "journal: not UTF-8": journal(lambda p, r: p.write_bytes(b"0badc0de \xff\xfe\n")),
    "journal: a record of other types": journal_line('{"n": 99, "set": {"counters": "many"}}'),
    "journal: an event of other types": journal_line('{"n": 99, "event": {"serial": 1}}'),
    "journal: NaN": journal_line('{"n": 99, "set": {"mach_speed": NaN}}'),
    "journal: not an object": journal_line("[99]"),
    "lock: a directory": lambda p, r: directory(p.with_name(p.name + ".lock"), r),
}
LINE_MUTATIONS: dict[str, Mutate] = {
    **FILE,
    "another schema version": sql("UPDATE meta SET value = '2' WHERE key = 'schema'"),
    "no schema": sql("DELETE FROM meta"),
    "another program's table": sql("CREATE TABLE other (x)"),
    "a table with other columns": sql("DROP TABLE episodes", "CREATE TABLE episodes (id, what)"),
    "a segment of other types": sql(
        "INSERT INTO segments VALUES ('filler', 'soon', 5, 'down', 'x', '')"
    ),
    "a count that is a blob": sql("INSERT INTO counts VALUES ('filler', 1, x'00', 0, 0, 0, '')"),
    "a huge reason": sql("UPDATE segments SET reason = ? WHERE rowid = 1", args=("r" * HUGE,)),
    "open state a list": sql("UPDATE state SET document = '[1, 2]'"),
    "open state not JSON": sql("UPDATE state SET document = '{\"trackers\": '"),
    "open state not UTF-8": sql("UPDATE state SET document = CAST(x'7b22ff223a317d' AS TEXT)"),
    "open state of other types": sql(
        'UPDATE state SET document = \'{"trackers": 5, "reset_at": "x"}\''
    ),
    "open state NaN": sql("UPDATE state SET document = '{\"reset_at\": NaN}'"),
    "an episode not JSON": sql("UPDATE episodes SET document = 'not json'"),
    "an episode of other types": sql('UPDATE episodes SET document = \'{"id": "x"}\''),
    "lock: a directory": UNIT_MUTATIONS["lock: a directory"],
}
RANDOM: tuple[Mutate, ...] = (truncated, bit_flips, byte_run, garbage)


# -- opening, and what must hold -----------------------------------------------------------------------
def opened(what: str, path: Path, start: Callable[[], Any]) -> tuple[Any, list[str]] | None:
    """Open with ``start`` (returns the object and its store's problems); None when refused. A
    refusal is one line naming the file; any other exception fails the test; memory is bounded."""
    tracemalloc.start()
    try:
        return start()  # type: ignore[no-any-return]
    except StoreError as exc:
        text = str(exc)
        assert "\n" not in text and str(path) in text and len(text) < 600, f"{what}: {text!r}"
        return None
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert peak < PEAK_BYTES, f"{what}: {peak / 2**20:.0f} MB of Python memory to open"


def check_problems(what: str, path: Path, problems: list[str]) -> None:
    for problem in problems:
        assert "\n" not in problem and 0 < len(problem) < 1000, f"{what}: {problem!r}"
        assert "unreadable-" in problem, f"{what}: the problem does not say where: {problem!r}"
    if problems:
        aside = [p.name for p in path.parent.iterdir() if ".unreadable-" in p.name]
        assert aside, f"{what}: {problems} but nothing moved aside"


def open_unit(what: str, path: Path) -> bool:
    """True when the unit started (and checked), False when it refused."""
    clock = FakeClock(6_000.0)

    def start() -> tuple[Unit, list[str]]:
        store = Store(path, "u")
        return Unit(cell_unit(UNIT), clock, store), store.problems

    got = opened(what, path, start)
    if got is None:
        return False
    unit, problems = got
    check_problems(what, path, problems)
    history = unit.admin().alarm_history
    raised = [e for e in history if e.id == STORE_UNREADABLE]
    assert len(raised) == len(problems), f"{what}: {problems} but alarms {raised}"
    assert unit.command(Cmd.RESET).accepted, what  # it works, and writes
    unit.em_count("em", "processed", 0, 3)
    unit.admin()
    unit.close()
    again = Store(path, "u")  # the next start is clean
    assert again.problems == [], f"{what}: again {again.problems}"
    doc = again.load()
    assert doc is not None and doc["counters"]["processed"][0][0] >= 3, what
    again.close()
    return True


def open_line(what: str, path: Path) -> bool:
    def start() -> tuple[SimLine, list[str]]:
        sim = started(cell_doc(), str(path))
        assert sim.line.store is not None
        return sim, sim.line.store.problems

    got = opened(what, path, start)
    if got is None:
        return False
    sim, problems = got
    check_problems(what, path, problems)
    sim.run_until(8)  # reset and start: facts, episodes and the state written
    now = round(sim.t * NS)
    assert sim.line.window("lifetime", now).scopes, what
    sim.line.query_episodes()
    sim.line.close()
    again = LineStore(path, "sim")
    assert again.problems == [], f"{what}: again {again.problems}"
    again.close()
    return True


STORES: dict[
    str, tuple[Callable[[Path], None], dict[str, Mutate], Callable[[str, Path], bool], str]
] = {
    "unit": (used_unit_store, UNIT_MUTATIONS, open_unit, "u.sqlite3"),
    "line": (used_line_store, LINE_MUTATIONS, open_line, "line.sqlite3"),
}
REFUSED = ("a directory", "a symlink to /dev/zero", "lock: a directory")


@pytest.mark.parametrize("store", list(STORES))
def test_every_corrupted_store_starts_clean_or_refuses_in_one_line(
    tmp_path: Path, store: str
) -> None:
    make, mutations, open_it, name = STORES[store]
    pristine = tmp_path / "pristine"
    pristine.mkdir()
    make(pristine / name)
    rng = random.Random(SEED)
    cases = [(what, m) for what, m in mutations.items()]
    cases += [
        (f"random {i}: {m.__name__}", m)
        for i in range(RANDOM_PER_STORE)
        for m in [rng.choice(RANDOM)]
    ]
    outcomes: dict[str, bool] = {}
    t0 = time.monotonic()
    for n, (what, mutate) in enumerate(cases):
        d = tmp_path / f"case{n}"
        shutil.copytree(pristine, d, symlinks=True)
        mutate(d / name, rng)
        outcomes[what] = open_it(f"{store} store, {what}", d / name)
        shutil.rmtree(d)
    refused = sorted(w for w, ok in outcomes.items() if not ok)
    # a directory or a device where the file (or its lock) should be is refused; all else starts
    assert refused == sorted(REFUSED), refused
    assert time.monotonic() - t0 < 30


def test_a_journal_longer_than_the_bound_is_read_up_to_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "u.sqlite3"
    used_unit_store(path)
    monkeypatch.setattr(persistence_module, "JOURNAL_MAX", 4096)
    s = Store(path, "u")
    for i in range(200):
        s.append([{"set": {"mach_speed": float(i)}}])
    s.close()
    again = Store(path, "u")
    assert len(again.problems) == 1 and "longer than 4096 bytes" in again.problems[0]
    doc = again.load()
    assert doc is not None and 0 < doc["mach_speed"] < 199  # the records before the bound
    again.close()


#: As root (CI): the store's directory is bind-mounted read-only in a mount namespace of a child
#: process (root writes a file of mode 0444, but not on a read-only mount).
READ_ONLY_CHILD = """
import sys
from packml_ros2.core import Store, StoreError
try:
    Store(sys.argv[1], "u")
except StoreError as exc:
    print(f"refused: {exc}")
else:
    print("opened")
"""
MOUNT_READ_ONLY = 'mount --bind "$1" "$1" && mount -o remount,ro,bind "$1" && shift && exec "$@"'


def test_a_read_only_store_is_refused_in_one_line(tmp_path: Path) -> None:
    path = tmp_path / "u.sqlite3"
    used_unit_store(path)
    path.chmod(0o444)
    if os.geteuid() != 0:
        with pytest.raises(StoreError, match="not writable"):
            Store(path, "u")
        return
    run = subprocess.run(
        ["unshare", "--mount", "--propagation", "private", "sh", "-c", MOUNT_READ_ONLY, "sh",
         str(tmp_path), sys.executable, "-c", READ_ONLY_CHILD, str(path)],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    if run.returncode != 0 and "mount" in run.stderr:
        pytest.skip(f"no mount namespace here: {run.stderr.strip()[:200]}")
    assert run.returncode == 0, run.stderr
    (line,) = run.stdout.splitlines()
    assert line.startswith("refused: ") and "not writable" in line, line
    assert "Traceback" not in run.stderr


# -- as the user runs them --------------------------------------------------------------------------
def write_cell(tmp_path: Path) -> Path:
    doc = {
        "cell": f"st{os.getpid()}",
        "units": {"u": {**UNIT, "persistence": {"path": str(tmp_path / "{unit}.sqlite3")}}},
        "coordinator": {"start_order": ["u"]},
        "line": {"store": str(tmp_path / "line.sqlite3")},
    }
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def wait_for(proc: NodeProcess, text: str, timeout: float = 30.0) -> str:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        out = proc.output()
        if text in out or not proc.running():
            return out
        time.sleep(0.05)
    return proc.output()


def test_unit_node_and_coordinator_log_a_corrupted_store_or_exit_in_one_line(
    tmp_path: Path,
) -> None:
    cell = write_cell(tmp_path)
    (tmp_path / "u.sqlite3").write_bytes(b"SQLite format 3\x00" + bytes(range(256)) * 8)
    (tmp_path / "line.sqlite3").write_bytes(b"not a database at all" * 100)
    procs = [
        NodeProcess("unit", ["-m", "packml_ros2.unit_node", str(cell), "u"], tmp_path),
        NodeProcess("coordinator", ["-m", "packml_ros2.coordinator_node", str(cell)], tmp_path),
    ]
    try:
        unit_out = wait_for(procs[0], " up: ")  # (after the problem's line)
        line_out = wait_for(procs[1], " up: ")
        assert procs[0].running() and procs[1].running(), unit_out + line_out
    finally:
        for p in procs:  # (a SIGINT before the spin began may end it with -2: not the point here)
            p.stop()
        unit_out, line_out = procs[0].output(), procs[1].output()
        for p in procs:
            p.close()
    for out, prefix in (
        (unit_out, "persistence: u.sqlite3 could not be read"),
        (line_out, "line store: line.sqlite3 is not a line store"),
    ):
        assert prefix in out and "Traceback" not in out, out
    assert len([n for n in os.listdir(tmp_path) if ".unreadable-" in n]) == 2

    for name in ("u.sqlite3", "line.sqlite3"):  # a directory in the files' place
        target = tmp_path / name
        for extra in tmp_path.glob(name + "*"):
            extra.unlink() if extra.is_file() else shutil.rmtree(extra)
        target.mkdir()
    for argv, who in (
        (["-m", "packml_ros2.unit_node", str(cell), "u"], "unit_node"),
        (["-m", "packml_ros2.coordinator_node", str(cell)], "coordinator"),
    ):
        result = subprocess.run(
            [sys.executable, *argv], capture_output=True, text=True, timeout=60, check=False
        )
        lines = result.stderr.strip().splitlines()
        assert result.returncode == 2 and len(lines) == 1, result.stderr
        assert lines[0].startswith(f"{who}: {tmp_path}") and "is a directory" in lines[0], lines


# -- the self-signed certificate an OPC UA server or a PLC bridge made before --------------------------
CERT_MUTATIONS: dict[str, Mutate] = {
    "certificate: garbage": lambda d, r: garbage(d / "server_cert.der", r),
    "certificate: truncated": lambda d, r: truncated(d / "server_cert.der", r),
    "certificate: zero length": lambda d, r: zero_length(d / "server_cert.der", r),
    "certificate: bit flips": lambda d, r: bit_flips(d / "server_cert.der", r),
    "certificate: a directory": lambda d, r: directory(d / "server_cert.der", r),
    "certificate: a symlink to /dev/zero": lambda d, r: dev_zero(d / "server_cert.der", r),
    "certificate: huge": lambda d, r: (d / "server_cert.der").write_bytes(b"0" * HUGE),
    "key: garbage": lambda d, r: garbage(d / "server_key.pem", r),
    "key: of another pair": lambda d, r: (d / "server_key.pem").write_bytes(
        (d.parent / "other" / "server_key.pem").read_bytes()
    ),
    "key: missing": lambda d, r: (d / "server_key.pem").unlink(),
}


def test_a_damaged_certificate_is_moved_aside_and_made_again(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    import asyncio

    from asyncua.crypto import uacrypto

    from packml_ros2.opcua.server import own_certificate

    def make(folder: Path) -> tuple[Path, Path]:
        return asyncio.run(own_certificate(folder, "urn:packml_ros2:t", "t", "127.0.0.1"))

    pristine, other = tmp_path / "pristine", tmp_path / "other"
    make(pristine)
    make(other)
    kept = (pristine / "server_cert.der").read_bytes()
    assert (
        make(pristine) and (pristine / "server_cert.der").read_bytes() == kept
    )  # a good pair stays
    rng = random.Random(SEED)
    for n, (what, mutate) in enumerate(CERT_MUTATIONS.items()):
        d = tmp_path / f"case{n}"
        shutil.copytree(pristine, d, symlinks=True)
        mutate(d, rng)
        caplog.clear()
        got = opened(what, d, lambda d=d: make(d))
        assert got is not None, what
        cert = asyncio.run(uacrypto.load_certificate(d / "server_cert.der"))
        key = asyncio.run(uacrypto.load_private_key(d / "server_key.pem"))
        assert cert.public_key().public_numbers() == key.public_key().public_numbers(), what
        if what != "key: missing":  # (one of the pair made, then killed: made again silently)
            assert any(".unreadable-" in p.name for p in d.iterdir()), what
            assert "moved aside" in caplog.text and "\n" not in caplog.text.strip(), (
                what,
                caplog.text,
            )
