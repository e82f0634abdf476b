"""Persistence of a line's performance: every fact, every episode and the open state, in SQLite.

One file per cell (``line.store``, default ``~/.local/state/packml_ros2/<cell>/line.sqlite3``):

- ``segments`` and ``counts``: the facts (:mod:`.ledger`), appended, never changed;
- ``episodes``: one row per stop episode, replaced while it is open;
- ``state``: the open state of :class:`~.performance.Performance` (what the units were doing
  since when, the open episode), one row.

Write-ahead: the facts, episodes and open state an input produced are written in **one
transaction, committed before anything of that input is published or answered**. SQLite in WAL
mode writes the commit to its log with one ``write()``: a coordinator killed at any moment
(SIGKILL, a crash) loses nothing it published, and a restart continues from the last commit (the
units' latched transitions tell what happened meanwhile). Without ``fsync`` (``synchronous =
NORMAL``), a power loss can lose the last commits the OS had not written to disk yet.

A second coordinator of the same cell cannot open the store (``<file>.lock``, as the units'
stores); a file that is not a line store is moved aside (``<file>.unreadable-<UTC time>``) and
the line starts with an empty one (:attr:`LineStore.problems` says so).
"""

from __future__ import annotations

import contextlib
import json
import os
import sqlite3
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from ..persistence import (
    StoreError,
    lock_path,
    lock_store,
    move_aside,
    not_a_file,
    not_writable,
    one_line,
    os_reason,
    sqlite_damage,
    strict_json,
)
from .episodes import Episode
from .ledger import RECENT, Count, Fact, Ledger, Segment
from .losses import Totals

SCHEMA_VERSION = 1
_TABLES = {"segments", "counts", "episodes", "state", "meta"}
_FAR = 2**62
#: Inputs a line store that cannot be written (a full disk) holds in memory until it can.
PENDING_MAX = 100_000
TEXT_MAX = (
    2**20
)  #: bytes of a stored text (a reason, an episode, the open state): memory stays bounded
_SCHEMA = (
    "CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)",
    "CREATE TABLE IF NOT EXISTS segments (scope TEXT NOT NULL, start INTEGER NOT NULL,"
    " end INTEGER NOT NULL, bucket TEXT NOT NULL, reason TEXT NOT NULL, shift TEXT NOT NULL)",
    "CREATE INDEX IF NOT EXISTS segments_end ON segments (end)",
    "CREATE INDEX IF NOT EXISTS segments_shift ON segments (shift)",
    "CREATE TABLE IF NOT EXISTS counts (scope TEXT NOT NULL, t INTEGER NOT NULL,"
    " processed INTEGER NOT NULL, defective INTEGER NOT NULL, net INTEGER NOT NULL,"
    " good INTEGER NOT NULL, shift TEXT NOT NULL)",
    "CREATE INDEX IF NOT EXISTS counts_t ON counts (t)",
    "CREATE INDEX IF NOT EXISTS counts_shift ON counts (shift)",
    "CREATE TABLE IF NOT EXISTS episodes (id INTEGER PRIMARY KEY, start INTEGER NOT NULL,"
    " end INTEGER, root_unit TEXT NOT NULL, bucket TEXT NOT NULL, reason TEXT NOT NULL,"
    " document TEXT NOT NULL)",
    "CREATE INDEX IF NOT EXISTS episodes_start ON episodes (start)",
    "CREATE TABLE IF NOT EXISTS state (key TEXT PRIMARY KEY, document TEXT NOT NULL)",
)


class LineStore:
    """``LineStore(path, cell)``: open (lock, create, recover) the line store of ``cell``."""

    def __init__(self, path: str | os.PathLike[str], cell: str) -> None:
        self.path = Path(path)
        self.cell = cell
        self.problems: list[str] = []
        self.commits = 0
        #: why the store cannot be written now ('' = it can): what the line committed since is
        #: held in :attr:`pending` (bounded) and written with the next commit that succeeds
        self.failing = ""
        self.pending: list[
            tuple[Sequence[Fact], Sequence[tuple[Episode, str, str, str]], Mapping[str, Any] | None]
        ] = []
        self.pending_dropped = 0
        self._read_only = False
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            for where in (self.path, lock_path(self.path)):
                if (problem := not_a_file(where)) is not None:
                    raise problem
            self._lock = lock_store(self.path, f"line of {cell}")
        except (OSError, ValueError) as exc:
            raise self._cannot_open(exc) from None
        try:
            self.db = self._open()
        except (OSError, sqlite3.Error) as exc:
            os.close(self._lock)
            raise self._cannot_open(exc) from None

    def _cannot_open(self, exc: BaseException) -> StoreError:
        return StoreError(
            f"{self.path}: cannot open the line store of {self.cell}: {os_reason(exc)} "
            "(line.store of the cell file; store: false keeps it in memory)"
        )

    def _open(self) -> sqlite3.Connection:
        db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
        try:
            problem = _foreign(db)
        except sqlite3.DatabaseError as exc:
            if not_writable(exc):
                db.close()
                return self._unwritable(exc)
            problem = one_line(exc)
        if problem:
            with contextlib.suppress(Exception):
                db.close()
            db = self._aside(f"is not a line store ({problem})")
        try:
            _prepare(db)
        except sqlite3.Error as exc:
            db.close()
            if not_writable(exc):
                return self._unwritable(exc)
            raise
        return db

    def _unwritable(self, exc: BaseException) -> sqlite3.Connection:
        """A store that cannot be written now (a full disk: no room for its -wal and -shm): it
        is read as it is (never moved aside) and the next commit tries to open it for writing."""
        self.failing = f"{self.path.name} cannot be written ({one_line(exc)})"
        self._read_only = True
        for query in ("mode=ro", "immutable=1"):
            db = sqlite3.connect(f"file:{self.path}?{query}", uri=True, check_same_thread=False)
            try:
                if not _foreign(db) and "meta" in _tables(db):
                    return db
            except sqlite3.Error:
                db.close()
                continue
            db.close()  # (empty: the line starts with an empty store in memory)
            break
        db = sqlite3.connect(":memory:", isolation_level=None, check_same_thread=False)
        for statement in _SCHEMA:
            db.execute(statement)
        return db

    def _aside(self, why: str) -> sqlite3.Connection:
        aside = move_aside(self.path, "-wal", "-shm")
        self.problems.append(
            f"{self.path.name} {why}: moved aside to {aside.name}; the line starts with an empty one"
        )
        return sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)

    def start_over(self, why: str) -> None:
        """Move the store aside and continue with an empty one (what it holds cannot be used:
        ``why``, a sentence, goes to :attr:`problems`)."""
        self.db.close()
        self.db = self._aside(why)
        self.db.close()
        self.db = self._open()

    # -- writing -----------------------------------------------------------------------------------
    def commit(
        self,
        facts: Sequence[Fact],
        episodes: Sequence[tuple[Episode, str, str, str]],
        state: Mapping[str, Any] | None,
    ) -> None:
        """One input's facts, episodes ((episode, root unit, bucket, reason)) and open state, in
        one transaction. A store that cannot be written (a full disk) keeps them in
        :attr:`pending` (:attr:`failing` says why) and writes them with the next commit that
        succeeds."""
        if self.failing:
            self._hold(facts, episodes, state)
            try:
                if self._read_only:
                    db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
                    try:
                        _prepare(db)
                    except BaseException:
                        db.close()
                        raise
                    self.db.close()
                    self.db, self._read_only = db, False
                held, self.pending = self.pending, []
                try:
                    for f, e, s in held:
                        self._write(f, e, s)
                except BaseException:
                    self.pending = held + self.pending
                    raise
            except sqlite3.Error as exc:
                if not not_writable(exc):
                    raise
                self.failing = f"{self.path.name} cannot be written ({one_line(exc)})"
                return
            self.failing = ""
            return
        try:
            self._write(facts, episodes, state)
        except sqlite3.Error as exc:
            if not not_writable(exc):
                raise
            self.failing = f"{self.path.name} cannot be written ({one_line(exc)})"
            self._hold(facts, episodes, state)

    def _hold(
        self,
        facts: Sequence[Fact],
        episodes: Sequence[tuple[Episode, str, str, str]],
        state: Mapping[str, Any] | None,
    ) -> None:
        """Keep an input's writes until the store takes them again (at most :data:`PENDING_MAX`
        inputs: the oldest beyond are dropped and counted)."""
        self.pending.append((list(facts), list(episodes), state))
        if len(self.pending) > PENDING_MAX:
            del self.pending[0]
            self.pending_dropped += 1

    def _write(
        self,
        facts: Sequence[Fact],
        episodes: Sequence[tuple[Episode, str, str, str]],
        state: Mapping[str, Any] | None,
    ) -> None:
        db = self.db
        db.execute("BEGIN")
        try:
            segs = [
                (f.scope, f.start, f.end, f.bucket, f.reason, f.shift)
                for f in facts
                if isinstance(f, Segment)
            ]
            if segs:
                db.executemany("INSERT INTO segments VALUES (?, ?, ?, ?, ?, ?)", segs)
            counts = [
                (f.scope, f.t, f.processed, f.defective, f.net, f.good, f.shift)
                for f in facts
                if isinstance(f, Count)
            ]
            if counts:
                db.executemany("INSERT INTO counts VALUES (?, ?, ?, ?, ?, ?, ?)", counts)
            for ep, unit, bucket, reason in episodes:
                db.execute(
                    "INSERT OR REPLACE INTO episodes VALUES (?, ?, ?, ?, ?, ?, ?)",
                    (ep.id, ep.start, ep.end, unit, bucket, reason, json.dumps(ep.to_dict())),
                )
            if state is not None:
                db.execute(
                    "INSERT OR REPLACE INTO state VALUES ('performance', ?)", (json.dumps(state),)
                )
            db.execute("COMMIT")
        except BaseException:
            with contextlib.suppress(sqlite3.Error):
                db.execute("ROLLBACK")
            raise
        self.commits += 1

    def note(self, key: str, value: Mapping[str, Any] | None) -> None:
        """Keep a small document under ``key`` (None removes it), committed at once: the cell
        command in flight (``command``), which a restarted coordinator reports. Best effort: a
        store that cannot be written (a full disk) keeps nothing (:attr:`failing` says why)."""
        try:
            if value is None:
                self.db.execute("DELETE FROM meta WHERE key = ?", (f"note:{key}",))
            else:
                self.db.execute(
                    "INSERT OR REPLACE INTO meta (key, value) VALUES (?, ?)",
                    (f"note:{key}", json.dumps(value)),
                )
        except sqlite3.Error as exc:
            if not not_writable(exc):
                raise
            self.failing = f"{self.path.name} cannot be written ({one_line(exc)})"

    def noted(self, key: str) -> dict[str, Any] | None:
        """The document :meth:`note` kept under ``key`` (None: none, or not one)."""
        row = self.db.execute("SELECT value FROM meta WHERE key = ?", (f"note:{key}",)).fetchone()
        doc = _document(row[0]) if row is not None else None
        return doc if isinstance(doc, dict) else None

    # -- reading -----------------------------------------------------------------------------------
    def state(self) -> dict[str, Any] | None:
        """The open state; ValueError when it is not one (the line moves the store aside)."""
        row = self.db.execute("SELECT document FROM state WHERE key = 'performance'").fetchone()
        if row is None:
            return None
        doc = _document(row[0])
        if not isinstance(doc, dict):
            raise ValueError("the open state is not a JSON object")
        return doc

    def totals(self, a: int | None, b: int | None) -> dict[str, Totals]:
        lo, hi = (-_FAR if a is None else a), (_FAR if b is None else b)
        out: dict[str, Totals] = {}
        for scope, bucket, reason, ns in self.db.execute(
            "SELECT scope, bucket, reason, SUM(MIN(end, ?2) - MAX(start, ?1)) FROM segments"
            " WHERE end > ?1 AND start < ?2 GROUP BY scope, bucket, reason",
            (lo, hi),
        ):
            out.setdefault(scope, Totals()).add_time(bucket, reason, int(ns))
        for scope, p, d, net, good in self.db.execute(
            "SELECT scope, SUM(processed), SUM(defective), SUM(net), SUM(good) FROM counts"
            " WHERE t >= ?1 AND t < ?2 GROUP BY scope",
            (lo, hi),
        ):
            out.setdefault(scope, Totals()).add_count(int(p), int(d), int(net), int(good))
        return out

    def shift_totals(self, keys: Iterable[str] | None = None) -> dict[str, dict[str, Totals]]:
        out: dict[str, dict[str, Totals]] = {}
        wanted = None if keys is None else set(keys)
        for shift, scope, bucket, reason, ns in self.db.execute(
            "SELECT shift, scope, bucket, reason, SUM(end - start) FROM segments WHERE shift != ''"
            " GROUP BY shift, scope, bucket, reason"
        ):
            if wanted is None or shift in wanted:
                out.setdefault(shift, {}).setdefault(scope, Totals()).add_time(
                    bucket, reason, int(ns)
                )
        for shift, scope, p, d, net, good in self.db.execute(
            "SELECT shift, scope, SUM(processed), SUM(defective), SUM(net), SUM(good) FROM counts"
            " WHERE shift != '' GROUP BY shift, scope"
        ):
            if wanted is None or shift in wanted:
                out.setdefault(shift, {}).setdefault(scope, Totals()).add_count(
                    int(p), int(d), int(net), int(good)
                )
        return out

    def shift_keys(self) -> list[str]:
        rows = self.db.execute(
            "SELECT shift, MIN(start) FROM segments WHERE shift != '' GROUP BY shift ORDER BY 2"
        )
        return [r[0] for r in rows]

    def restore_ledger(self, ledger: Ledger, reset_at: int | None) -> None:
        """The ledger's running windows as the facts give them."""
        latest = self.db.execute(
            "SELECT MAX(m) FROM (SELECT MAX(end) AS m FROM segments UNION ALL SELECT MAX(t) FROM counts)"
        ).fetchone()[0]
        ledger.lifetime = self.totals(None, None)
        ledger.reset_at = reset_at
        ledger.reset = (
            self.totals(reset_at, None)
            if reset_at is not None
            else {s: t.copy() for s, t in ledger.lifetime.items()}
        )
        ledger.shifts = self.shift_totals()
        ledger.latest = int(latest or 0)
        horizon = ledger.latest - RECENT
        recent: list[Fact] = [
            Segment(*r)
            for r in self.db.execute(
                "SELECT scope, start, end, bucket, reason, shift FROM segments WHERE end >= ? ORDER BY rowid",
                (horizon,),
            )
        ]
        recent += [
            Count(*r)
            for r in self.db.execute(
                "SELECT scope, t, processed, defective, net, good, shift FROM counts WHERE t >= ? ORDER BY rowid",
                (horizon,),
            )
        ]
        ledger.recent.clear()
        ledger.recent.extend(sorted(recent, key=lambda f: f.end if isinstance(f, Segment) else f.t))

    def episodes(
        self,
        since: int | None = None,
        until: int | None = None,
        unit: str | None = None,
        reason: str = "",
        bucket: str = "",
        open_only: bool = False,
        limit: int = 100,
    ) -> tuple[list[Episode], int]:
        """Episodes newest first, filtered (see ``QueryEpisodes.srv``); and how many matched."""
        where: list[str] = []
        args: list[Any] = []
        if since is not None:
            where.append("(end IS NULL OR end >= ?)")
            args.append(since)
        if until is not None:
            where.append("start < ?")
            args.append(until)
        if unit is not None:
            where.append("root_unit = ?")
            args.append(unit)
        if reason:
            where.append("instr(lower(reason), lower(?)) > 0")
            args.append(reason)
        if bucket:
            where.append("bucket = ?")
            args.append(bucket)
        if open_only:
            where.append("end IS NULL")
        clause = f" WHERE {' AND '.join(where)}" if where else ""
        total = int(self.db.execute(f"SELECT COUNT(*) FROM episodes{clause}", args).fetchone()[0])
        rows = self.db.execute(
            f"SELECT document FROM episodes{clause} ORDER BY start DESC, id DESC LIMIT ?",
            [*args, limit],
        )
        return _episodes(rows), total

    def recent_episodes(self, n: int) -> list[Episode]:
        rows = self.db.execute(
            "SELECT document FROM episodes WHERE end IS NOT NULL ORDER BY id DESC LIMIT ?", (n,)
        )
        return _episodes(rows)[::-1]

    def close(self) -> None:
        if self._lock < 0:
            return
        self.db.close()
        os.close(self._lock)
        self._lock = -1


def _prepare(db: sqlite3.Connection) -> None:
    """WAL, the tables, the schema's version (writes: raises on a full disk)."""
    db.execute("PRAGMA journal_mode=WAL")
    db.execute("PRAGMA synchronous=NORMAL")
    for statement in _SCHEMA:
        db.execute(statement)
    db.execute(
        "INSERT OR IGNORE INTO meta (key, value) VALUES ('schema', ?)", (str(SCHEMA_VERSION),)
    )


def _tables(db: sqlite3.Connection) -> set[str]:
    return {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}


def _document(text: Any) -> Any:
    """A stored JSON document, or None when it is not one."""
    try:
        return strict_json(text)
    except (TypeError, ValueError):
        return None


def _episodes(rows: Iterable[tuple[Any, ...]]) -> list[Episode]:
    """The episodes of ``rows`` (a document each); the checks at opening make a bad one rare (a
    damage since), which is left out rather than failing every query."""
    out = []
    for (text,) in rows:
        with contextlib.suppress(TypeError, ValueError, KeyError, AttributeError):
            d = _document(text)
            if isinstance(d, dict):
                out.append(Episode.from_dict(d))
    return out


def _columns() -> dict[str, list[tuple[str, str, int]]]:
    """Each table's (column, declared type, not null), as :data:`_SCHEMA` declares them."""
    db = sqlite3.connect(":memory:")
    for statement in _SCHEMA:
        db.execute(statement)
    out = {t: [(c[1], c[2], c[3]) for c in db.execute(f"PRAGMA table_info({t})")] for t in _TABLES}
    db.close()
    return out


_COLUMNS = _columns()
_SQL_TYPES = {"INTEGER": "integer", "TEXT": "text"}


def _bad_row(table: str) -> str:
    """A query of the first row of ``table`` whose values are not of its declared types (a
    text longer than :data:`TEXT_MAX` counts as one)."""
    checks = []
    for name, kind, notnull in _COLUMNS[table]:
        allowed = f"'{_SQL_TYPES[kind]}'" + ("" if notnull else ", 'null'")
        checks.append(f"typeof({name}) NOT IN ({allowed})")
        if kind == "TEXT":
            checks.append(f"length(CAST({name} AS BLOB)) > {TEXT_MAX}")
    return f"SELECT rowid FROM {table} WHERE {' OR '.join(checks)} LIMIT 1"


_BAD_ROWS = {t: _bad_row(t) for t in sorted(_TABLES)}


def _foreign(db: sqlite3.Connection) -> str:
    """Why the file is not a line store of this version ('' = it is, or it is empty): its tables,
    their columns, the schema, and the type of every stored value (one scan of each table)."""
    tables = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
    if not tables:
        return ""
    if damage := sqlite_damage(db):
        return damage
    if tables - _TABLES or "meta" not in tables:
        return f"it holds the tables {', '.join(sorted(tables))}"
    row = db.execute("SELECT value FROM meta WHERE key = 'schema'").fetchone()
    if row is None or row[0] != str(SCHEMA_VERSION):
        return (
            f"schema {str(row[0])[:20] if row else 'unknown'}, this version reads {SCHEMA_VERSION}"
        )
    for table in sorted(tables):
        columns = [(c[1], c[2], c[3]) for c in db.execute(f"PRAGMA table_info({table})")]
        if columns != _COLUMNS[table]:
            return f"the table {table} has other columns"
        bad = db.execute(_BAD_ROWS[table]).fetchone()
        if bad is not None:
            return f"row {bad[0]} of the table {table} holds a value of another type or size"
    return ""
