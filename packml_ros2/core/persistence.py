"""Persistence of a unit's admin data (times, counters, alarm history, stop reason, sequence): a
snapshot, a write-ahead journal of the changes since, a lock, and recovery from a bad file.

Files of a store at ``path`` (one store per unit; the configuration names it):

- ``path``: SQLite (WAL), one row per unit holding the **snapshot** document, replaced in one
  transaction periodically (``persistence.period``) and when the unit closes;
- ``path.journal``: the **changes** since the snapshot, one line each (``crc32 json``), each
  input's changes appended with one ``write()`` *before* the unit answers or publishes it
  (write-ahead), so nothing a client was told is lost; a snapshot empties it;
- ``path.lock``: held (``flock``) while a unit uses the store, naming the holder's process: two
  units with the same cell/unit name cannot share a store (:class:`StoreLocked`).

Durability: a process killed at any moment (SIGKILL, a crash) loses nothing it answered or
published: once ``write()`` returned, the bytes are the kernel's, and the next start reads them.
No ``fsync``: a power loss or a kernel crash can lose what the kernel had not written to the disk
yet (Linux writes dirty pages back within about 30 s), and can tear the journal's last line; the
reader keeps every whole record before a damaged one.

Recovery: a file that is not a store of this version (garbage, another program's database,
another schema, a document of the wrong types) or a damaged journal does not stop the unit: it
is moved aside (``path.unreadable-<UTC time>``), the unit starts with what could be read (or
empty), and :attr:`Store.problems` says what happened (the unit logs it and raises its
``store_unreadable`` alarm).

A store that cannot be *written* now (a full disk, an I/O error: :func:`not_writable`) is not
unreadable: it is never moved aside. It opens read-only (:attr:`Store.failing` says why), a
journal write that fails leaves no torn line, and a write raises :class:`NotWritten`, which the
unit's :class:`~.durable.Durable` turns into its ``persistence_failing`` alarm and retries.
"""

from __future__ import annotations

import contextlib
import copy
import errno
import fcntl
import json
import math
import os
import socket
import sqlite3
import stat
import time
import zlib
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

SCHEMA_VERSION = 1
TABLE = "unit_admin"
_CREATE = (
    f"CREATE TABLE IF NOT EXISTS {TABLE} (unit TEXT PRIMARY KEY, schema INTEGER NOT NULL,"
    " saved_at REAL NOT NULL, document TEXT NOT NULL)"
)
#: Bounds of what a unit reads from its files (memory stays bounded whatever is on the disk): a
#: snapshot document (the alarm history's ring, the counters, the times: well under a megabyte)
#: and the journal (the changes of one ``persistence.period``).
DOCUMENT_MAX = 16 * 2**20
JOURNAL_MAX = 64 * 2**20
INT32_MAX = 2**31 - 1


class StoreError(RuntimeError):
    """The admin store cannot be opened: one line naming the file and why."""


class StoreLocked(StoreError):
    """The store is held by another unit (another process, or another store object here)."""


class NotWritten(RuntimeError):
    """A write to a store failed for a reason outside its content (a full disk, an I/O error, a
    file system turned read-only): what was to be written is not on the disk. One line."""


#: SQLite's primary result codes of a store that cannot be written *now* (not of a file that is
#: not a store): full, I/O error, cannot open, read-only, permission, busy, locked, no memory.
_TRANSIENT = frozenset({13, 10, 14, 8, 3, 5, 6, 7})
#: the same as SQLite words them, for an error that carries no code
_TRANSIENT_WORDS = ("full", "disk i/o", "unable to open", "readonly", "read-only", "locked",
                    "busy", "out of memory", "permission")  # fmt: skip


def not_writable(exc: BaseException) -> bool:
    """Whether ``exc`` says the store cannot be written now (its content may be intact): such a
    store is retried, never moved aside."""
    if isinstance(exc, OSError):
        return True
    if not isinstance(exc, sqlite3.OperationalError):
        return False
    code = getattr(exc, "sqlite_errorcode", None)
    if code is None:  # (raised by Python's sqlite3 itself, e.g. a TEXT that is not UTF-8: by what
        return any(words in str(exc).lower() for words in _TRANSIENT_WORDS)  # it says)
    return code & 0xFF in _TRANSIENT


def os_reason(exc: BaseException) -> str:
    if isinstance(exc, OSError):
        why = exc.strerror or type(exc).__name__
        return f"{Path(exc.filename).name}: {why}" if isinstance(exc.filename, str) else why
    return str(exc) or type(exc).__name__


def one_line(text: object, limit: int = 200) -> str:
    """``text`` (an exception, SQLite's report) on one line of at most ``limit`` characters."""
    flat = " ".join(str(text).split())
    return flat if len(flat) <= limit else flat[: limit - 3] + "..."


def not_a_file(path: Path) -> OSError | None:
    """Why ``path`` (which a store opens as a file) cannot be one: a directory, a device, a pipe
    (``/dev/zero`` would feed a reader forever), or None (a regular file, or nothing yet)."""
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        return None
    except OSError as exc:
        return exc
    if stat.S_ISREG(mode):
        return None
    what = "a directory" if stat.S_ISDIR(mode) else "not a regular file"
    return OSError(errno.EINVAL, f"is {what}", str(path))


def strict_json(text: str) -> Any:
    """JSON as Python writes it, without NaN or Infinity (no stored number is ever one)."""
    return json.loads(text, parse_constant=_no_constant, parse_float=_finite)


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a number a store holds")


def _finite(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"{text[:20]} is not a finite number")
    return value


class Store:
    """``Store(path, unit)``: open (lock, recover) the store of ``unit``; :meth:`load` returns the
    last document (snapshot and journal) or None, :meth:`append` journals changes, :meth:`save`
    writes a snapshot.

    Raises :class:`StoreError` when the files cannot be created, opened or written (the unit would
    otherwise lose its counts at the first change), :class:`StoreLocked` when another unit holds
    the store."""

    def __init__(self, path: str | os.PathLike[str], unit: str) -> None:
        self.path = Path(path)
        self.unit = unit
        #: What recovery did, one sentence each (the unit logs them and raises an alarm).
        self.problems: list[str] = []
        self.saves = 0
        self.appends = 0
        #: why the store cannot be written now ('' = it can): it opened on a full disk
        self.failing = ""
        self._db: sqlite3.Connection | None = None
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            for where in (self.path, lock_path(self.path)):
                if (problem := not_a_file(where)) is not None:
                    raise problem
            for where in (self.path.parent, self.path):  # (root passes access(): sqlite decides)
                if where.exists() and not os.access(where, os.W_OK):
                    raise PermissionError(13, f"{where} is not writable")
            self._lock = lock_store(self.path, unit)
        except (OSError, ValueError) as exc:
            raise self._cannot_open(exc) from None
        try:
            self._document, self._n = self._open()
            self._journal = os.open(
                _journal(self.path), os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644
            )
        except (OSError, ValueError, sqlite3.Error) as exc:
            os.close(self._lock)
            raise self._cannot_open(exc) from None
        except BaseException:
            os.close(self._lock)
            raise

    def _cannot_open(self, exc: BaseException) -> StoreError:
        return StoreError(
            f"{self.path}: cannot open the admin store of unit {self.unit}: {os_reason(exc)} "
            "(persistence.path of the cell file; persistence: false runs without one)"
        )

    # -- reading -----------------------------------------------------------------------------------
    @classmethod
    def read(cls, path: str | os.PathLike[str], unit: str) -> dict[str, Any] | None:
        """The document a unit opening the store would load, read-only and without the lock
        (tools, tests); raises if the files cannot be read."""
        db = sqlite3.connect(f"file:{Path(path)}?mode=ro", uri=True)
        try:
            document = _row(db, unit, str(path))
        finally:
            db.close()
        records, _ = _read_journal(_journal(Path(path)))
        return _replay(document, records)

    def load(self) -> dict[str, Any] | None:
        """The document as of the last change journaled: snapshot and journal."""
        return self._document

    def _open(self) -> tuple[dict[str, Any] | None, int]:
        document: dict[str, Any] | None = None
        db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
        try:
            document = _row(db, self.unit, str(self.path))  # (reads only: a foreign file stays)
            self._db = _configured(db)
        except (sqlite3.Error, ValueError, UnicodeDecodeError) as exc:
            with contextlib.suppress(Exception):
                db.close()
            if not_writable(exc):
                # A full disk (no room for the -wal and -shm files), an I/O error: the file may
                # be intact. Read it as it is, write nothing, and try again at the next save.
                return self._open_unwritable(exc)
            aside = move_aside(self.path, "-wal", "-shm")
            self.problems.append(
                f"{self.path.name} could not be read ({one_line(exc)}): moved aside to {aside.name}; the "
                "unit starts with the admin data its journal holds, if any"
            )
            self._db = _configured(
                sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
            )
        self._db.execute(_CREATE)
        journal = _journal(self.path)
        records, damage = _read_journal(journal)
        if damage is not None:
            aside = move_aside(journal)
            self.problems.append(
                f"{journal.name} is damaged ({one_line(damage)}): the {len(records)} records before the "
                f"damage were kept, the file moved aside to {aside.name}"
            )
            _write_journal(journal, records)
        try:
            document = _replay(document, records)
        except (ValueError, KeyError, TypeError) as exc:
            aside = move_aside(journal)
            self.problems.append(
                f"{journal.name} does not apply to the snapshot ({one_line(exc)}): moved aside to {aside.name}"
            )
        n = max((int(r["n"]) for r in records), default=0)
        if document is not None:
            n = max(n, int(document.get("journal", 0)))
        return document, n

    def _open_unwritable(self, exc: BaseException) -> tuple[dict[str, Any] | None, int]:
        """Open a store that cannot be written now: its document read-only (SQLite's read-only
        mode, or the main file alone when even that needs room the disk does not have), no
        connection for writing (:meth:`save` makes one when it can); :attr:`failing` says why."""
        self.failing = f"{self.path.name} cannot be written ({one_line(exc)})"
        self._db = None
        document = None
        for query in ("mode=ro", "immutable=1"):
            with contextlib.suppress(sqlite3.Error, ValueError, UnicodeDecodeError):
                db = sqlite3.connect(f"file:{self.path}?{query}", uri=True)
                try:
                    document = _row(db, self.unit, str(self.path))
                finally:
                    db.close()
                break
        else:
            raise StoreError(
                f"{self.path}: cannot read the admin store of unit {self.unit}: {one_line(exc)}"
            )
        records, _ = _read_journal(_journal(self.path))
        document = _replay(document, records)
        n = max((int(r["n"]) for r in records), default=0)
        if document is not None:
            n = max(n, int(document.get("journal", 0)))
        return document, n

    def _writable(self) -> sqlite3.Connection:
        """The connection for writing, made now if the store opened unwritable."""
        if self._db is None:
            db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
            try:
                _configured(db)
                db.execute(_CREATE)
            except BaseException:
                db.close()
                raise
            self._db = db
        return self._db

    # -- writing -----------------------------------------------------------------------------------
    def append(self, records: Iterable[Mapping[str, Any]]) -> None:
        """Journal changes (each a record: ``{"set": {key: value}}`` or ``{"event": {...}}``),
        numbered, with one ``write()`` (see the module docstring for what that guarantees)."""
        lines = []
        for record in records:
            self._n += 1
            lines.append(_line({"n": self._n, **record}))
        if lines:
            data = "".join(lines).encode()
            end = os.fstat(self._journal).st_size
            try:
                while data:
                    data = data[os.write(self._journal, data) :]
            except OSError as exc:  # (a full disk): no torn line stays behind the records before
                with contextlib.suppress(OSError):
                    os.ftruncate(self._journal, end)
                raise NotWritten(f"{_journal(self.path).name}: {os_reason(exc)}") from None
            self.appends += 1

    def save(self, document: dict[str, Any], now: float) -> None:
        """A snapshot of the whole document; the journal up to it is dropped. Raises
        :class:`NotWritten` when it cannot be written (a full disk): the store is as it was."""
        text = json.dumps({**document, "journal": self._n}, separators=(",", ":"))
        try:
            self._writable().execute(
                f"INSERT INTO {TABLE} (unit, schema, saved_at, document) VALUES (?, ?, ?, ?)"
                " ON CONFLICT(unit) DO UPDATE SET schema = excluded.schema,"
                " saved_at = excluded.saved_at, document = excluded.document",
                (self.unit, SCHEMA_VERSION, now, text),
            )
        except (sqlite3.Error, OSError) as exc:
            raise NotWritten(f"{self.path.name}: {one_line(exc)}") from None
        self.failing = ""
        os.ftruncate(self._journal, 0)  # records up to the snapshot's number are skipped anyway
        self.saves += 1

    def integrity_ok(self) -> bool:
        return bool(self._writable().execute("PRAGMA integrity_check").fetchone()[0] == "ok")

    def close(self) -> None:
        """Close the files and release the lock (idempotent)."""
        if self._lock < 0:
            return
        if self._db is not None:
            self._db.close()
        os.close(self._journal)
        os.close(self._lock)
        self._lock = -1


# -- the files -------------------------------------------------------------------------------------
def _journal(path: Path) -> Path:
    return path.with_name(path.name + ".journal")


def lock_path(path: Path) -> Path:
    return path.with_name(path.name + ".lock")


def lock_store(path: Path, unit: str) -> int:
    """Hold ``path.lock`` (released when the process ends, however it ends)."""
    fd = os.open(lock_path(path), os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        holder = os.pread(fd, 500, 0).decode(errors="replace").strip() or "another process"
        os.close(fd)
        if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            raise StoreLocked(
                f"{path} is in use by {holder}: two units with the same cell and unit name "
                "cannot share a store (give one another name or persistence path)"
            ) from None
        raise
    since = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime())
    text = f"process {os.getpid()} on {socket.gethostname()} (unit {unit}, since {since} UTC)\n"
    with contextlib.suppress(OSError):  # (the holder's name only: a full disk holds the lock too)
        os.ftruncate(fd, 0)
        os.pwrite(fd, text.encode(), 0)
    return fd


def _configured(db: sqlite3.Connection) -> sqlite3.Connection:
    db.execute("PRAGMA journal_mode=WAL")
    # NORMAL in WAL mode: a commit survives the process being killed (not a power loss) and
    # costs no fsync.
    db.execute("PRAGMA synchronous=NORMAL")
    return db


def _row(db: sqlite3.Connection, unit: str, where: str) -> dict[str, Any] | None:
    """The unit's snapshot, checked; ValueError when the file is not a store of this version."""
    tables = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
    if tables - {TABLE}:
        raise ValueError(f"not a PackML store: it holds the tables {', '.join(sorted(tables))}")
    if not tables:
        return None
    if damage := sqlite_damage(db):
        raise ValueError(damage)
    row = db.execute(
        f"SELECT schema, typeof(document), length(CAST(document AS BLOB)) FROM {TABLE} WHERE unit = ?",
        (unit,),
    ).fetchone()
    if row is None:
        return None
    schema, kind, size = row
    if schema != SCHEMA_VERSION:
        raise ValueError(
            f"unit {unit!r} was saved with schema {schema}, this version reads {SCHEMA_VERSION}"
        )
    if (
        kind != "text" or size > DOCUMENT_MAX
    ):  # (read only when it can be one: memory stays bounded)
        what = (
            f"{size} bytes, more than {DOCUMENT_MAX}"
            if kind == "text"
            else f"of SQLite type {kind}"
        )
        raise ValueError(f"the document of unit {unit!r} is {what}")
    text = db.execute(f"SELECT document FROM {TABLE} WHERE unit = ?", (unit,)).fetchone()[0]
    try:
        document = strict_json(text)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"the document of unit {unit!r} is not JSON ({exc})") from None
    problem = document_problem(document)
    if problem:
        raise ValueError(f"the document of unit {unit!r} is not valid: {problem}")
    return dict(document)


def _line(record: Mapping[str, Any]) -> str:
    text = json.dumps(record, separators=(",", ":"))
    return f"{zlib.crc32(text.encode()):08x} {text}\n"


def _read_journal(path: Path) -> tuple[list[dict[str, Any]], str | None]:
    """The journal's records up to the first damaged one, and what the damage is (None); at
    most :data:`JOURNAL_MAX` bytes of it are read."""
    if (problem := not_a_file(path)) is not None:
        return [], problem.strerror
    try:
        with path.open("rb") as f:
            data = f.read(min(os.fstat(f.fileno()).st_size, JOURNAL_MAX + 1))  # (a regular file)
    except FileNotFoundError:
        return [], None
    cut = None
    if len(data) > JOURNAL_MAX:
        data = data[: data.rfind(b"\n", 0, JOURNAL_MAX) + 1]
        cut = f"longer than {JOURNAL_MAX} bytes, the rest was not read"
    records: list[dict[str, Any]] = []
    for number, raw in enumerate(data.split(b"\n"), 1):
        if not raw:
            continue
        crc, _, text = raw.partition(b" ")
        try:
            if int(crc, 16) != zlib.crc32(text):
                raise ValueError("checksum")
            record = strict_json(text.decode())
            if not isinstance(record, dict) or not isinstance(record.get("n"), int):
                raise ValueError("not a record")
        except ValueError as exc:  # (UnicodeDecodeError too)
            return records, f"line {number}: {exc}"
        records.append(record)
    return records, cut


def _write_journal(path: Path, records: list[dict[str, Any]]) -> None:
    path.write_text("".join(_line(r) for r in records), encoding="utf-8")


def sqlite_damage(db: sqlite3.Connection) -> str:
    """What SQLite's own check finds wrong with the file ('' = nothing)."""
    damage = db.execute("PRAGMA quick_check(1)").fetchone()[0]
    return "" if damage == "ok" else f"damaged: {one_line(damage)}"


def move_aside(path: Path, *companions: str) -> Path:
    """Rename ``path`` (and its ``companions``: suffixes like -wal) to a name saying when and why."""
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    aside = path.with_name(f"{path.name}.unreadable-{stamp}")
    n = 1
    while aside.exists():
        n += 1
        aside = path.with_name(f"{path.name}.unreadable-{stamp}-{n}")
    path.rename(aside)
    for suffix in companions:
        extra = path.with_name(path.name + suffix)
        if extra.exists():
            extra.rename(aside.with_name(aside.name + suffix))
    return aside


def _replay(
    document: dict[str, Any] | None, records: list[dict[str, Any]]
) -> dict[str, Any] | None:
    """The snapshot with the journal's later records applied."""
    after = int(document.get("journal", 0)) if document is not None else 0
    records = [r for r in records if int(r["n"]) > after]
    if not records:
        return document
    out: dict[str, Any] = (
        copy.deepcopy(document) if document is not None else {}
    )  # (a record that does not apply leaves the snapshot as it was)
    for record in records:
        if "set" in record:
            out.update(record["set"])
        if "event" in record:
            alarms = out.setdefault("alarms", {"history": [], "history_dropped": 0})
            history: list[dict[str, Any]] = alarms.setdefault("history", [])
            event = record["event"]
            where = next(
                (i for i, e in enumerate(history) if e.get("serial") == event["serial"]), None
            )
            if where is None:
                history.insert(0, event)
                del history[int(record.get("keep", len(history))) :]  # the ring's capacity
            else:
                history[where] = event
            alarms["history_dropped"] = int(record.get("dropped", alarms.get("history_dropped", 0)))
    problem = document_problem(out)
    if problem:
        raise ValueError(problem)
    return out


# -- what a document must look like ----------------------------------------------------------------
_NUMBER = (int, float)
_EVENT_TYPES: Mapping[str, tuple[type, ...]] = {
    "id": (int,), "value": (int,), "message": (str,), "category": (int,), "kind": (int,),
    "time": _NUMBER,
}  # fmt: skip


def _numbers_by_index(x: Any) -> bool:
    return isinstance(x, dict) and all(
        isinstance(k, str)
        and k.isdigit()
        and len(k) < 6
        and isinstance(v, _NUMBER)
        and not isinstance(v, bool)
        and v >= 0
        for k, v in x.items()
    )


def _event_problem(e: Any) -> str | None:
    if not isinstance(e, dict):
        return "an event is not a mapping"
    for key, types in _EVENT_TYPES.items():
        if not isinstance(e.get(key), types) or isinstance(e.get(key), bool):
            return f"event field {key!r} is {e.get(key)!r}"[:200]
        if types == (int,) and not -INT32_MAX - 1 <= e[key] <= INT32_MAX:
            return f"event field {key!r} is out of the int32 range"
    if not 0 <= e["kind"] <= 3:
        return f"event kind {e['kind']} is not 0..3"
    return None


def document_problem(d: Any) -> str | None:
    """What is wrong with a stored document (types and shapes), or None."""
    if not isinstance(d, dict):
        return "not a mapping"
    sequence = d.get("sequence", 0)
    if not isinstance(sequence, int) or isinstance(sequence, bool) or not 0 <= sequence < 2**32:
        return f"sequence is {sequence!r} (not a uint32)"[:200]
    times = d.get("times", {})
    if not isinstance(times, dict):
        return "times is not a mapping"
    for key in ("mode_current", "mode_cumulative", "state_current", "state_cumulative"):
        if not _numbers_by_index(times.get(key, {})):
            return f"times.{key} is not a mapping of index to seconds"
    for key in ("acc_time_since_reset", "planned_stop"):
        if not isinstance(times.get(key, 0.0), _NUMBER):
            return f"times.{key} is not a number"
    counters = d.get("counters", {})
    if not isinstance(counters, dict) or not all(
        isinstance(v, list)
        and all(
            isinstance(p, list)
            and len(p) == 2
            and all(isinstance(x, int) and 0 <= x <= INT32_MAX for x in p)
            for p in v
        )
        for v in counters.values()
    ):
        return "counters are not lists of [Count, AccCount]"
    alarms = d.get("alarms", {})
    if not isinstance(alarms, dict) or not isinstance(alarms.get("history", []), list):
        return "alarms.history is not a list"
    if not isinstance(alarms.get("history_dropped", 0), int) or isinstance(
        alarms.get("history_dropped", 0), bool
    ):
        return "alarms.history_dropped is not a number"
    for e in alarms.get("history", []):
        problem = _event_problem(e)
        if problem:
            return f"alarms.history: {problem}"
    if d.get("stop_reason") is not None:
        problem = _event_problem(d["stop_reason"])
        if problem:
            return f"stop_reason: {problem}"
    recipe = d.get("recipe_current", 0)
    if not isinstance(recipe, int) or isinstance(recipe, bool) or not 0 <= recipe <= INT32_MAX:
        return f"recipe_current is {recipe!r} (not a recipe ID)"[:200]
    for key in ("mach_speed", "saved_at"):
        if not isinstance(d.get(key, 0.0), _NUMBER):
            return f"{key} is not a number"
    return None
