"""Persistence of a unit's admin data: times, counters, alarm history, stop reason and the
sequence number, in SQLite.

One row per unit holds a JSON document; every save replaces it in one transaction, so a process
killed at any moment leaves either the previous or the new document, never a mix (SQLite's atomic
commit; WAL journal). The state itself is never stored: a restarted unit is in Stopped.
"""

from __future__ import annotations

import json
import os
import sqlite3
from pathlib import Path
from typing import Any

SCHEMA_VERSION = 1


class StoreError(RuntimeError):
    """The admin store cannot be opened: one line naming the file and why."""


def _why(exc: BaseException) -> str:
    if isinstance(exc, OSError):
        return exc.strerror or type(exc).__name__
    return str(exc) or type(exc).__name__


class Store:
    """``Store(path, unit)``; :meth:`load` returns the last saved document or None.

    Raises :class:`StoreError` when the file cannot be created, opened or written (the unit would
    otherwise lose its counts at the first save)."""

    def __init__(self, path: str | os.PathLike[str], unit: str) -> None:
        self.path = Path(path)
        self.unit = unit
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            for where in (self.path.parent, self.path):  # (root passes access(): sqlite decides)
                if where.exists() and not os.access(where, os.W_OK):
                    raise PermissionError(13, f"{where} is not writable")
            self._db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
            self._db.execute("PRAGMA journal_mode=WAL")
            # NORMAL in WAL mode: a commit survives the process being killed (not a power loss)
            # and costs no fsync, so saving at every transition stays cheap.
            self._db.execute("PRAGMA synchronous=NORMAL")
            self._db.execute(
                "CREATE TABLE IF NOT EXISTS unit_admin ("
                " unit TEXT PRIMARY KEY, schema INTEGER NOT NULL, saved_at REAL NOT NULL,"
                " document TEXT NOT NULL)"
            )
        except (OSError, ValueError, sqlite3.Error) as exc:
            raise StoreError(
                f"{self.path}: cannot open the admin store of unit {unit}: {_why(exc)} "
                "(persistence.path of the cell file; persistence: false runs without one)"
            ) from None
        self.saves = 0

    def load(self) -> dict[str, Any] | None:
        row = self._db.execute(
            "SELECT schema, document FROM unit_admin WHERE unit = ?", (self.unit,)
        ).fetchone()
        if row is None:
            return None
        schema, document = row
        if schema != SCHEMA_VERSION:
            raise RuntimeError(
                f"{self.path}: unit {self.unit!r} was saved with schema {schema}, "
                f"this version reads {SCHEMA_VERSION}"
            )
        data: dict[str, Any] = json.loads(document)
        return data

    def save(self, document: dict[str, Any], now: float) -> None:
        text = json.dumps(document, separators=(",", ":"))
        self._db.execute(
            "INSERT INTO unit_admin (unit, schema, saved_at, document) VALUES (?, ?, ?, ?)"
            " ON CONFLICT(unit) DO UPDATE SET schema = excluded.schema,"
            " saved_at = excluded.saved_at, document = excluded.document",
            (self.unit, SCHEMA_VERSION, now, text),
        )
        self.saves += 1

    def integrity_ok(self) -> bool:
        return bool(self._db.execute("PRAGMA integrity_check").fetchone()[0] == "ok")

    def close(self) -> None:
        self._db.close()
