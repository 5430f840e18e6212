"""The default job database: one SQLite file in the data dir (`DATA/jobs.sqlite`).

WAL mode lets the HTTP handlers read while a worker thread writes, and it survives `kill -9`:
a committed row is on disk. One connection shared by all threads behind a lock: the
statements are tiny, and a single writer sidesteps SQLITE_BUSY between our own threads.
"""
from __future__ import annotations

import sqlite3
import threading
from pathlib import Path
from typing import Any, Sequence

from service.jobs.db.schema import DuplicateKey, Kind, Table, column_sql, create_statements, index_statements

DB_NAME = "jobs.sqlite"
TYPES = {Kind.TEXT: "TEXT", Kind.INTEGER: "INTEGER", Kind.REAL: "REAL"}  # SQLite REAL is 64-bit


class SqliteDatabase:
    insertion_order = "rowid"  # SQLite's own row counter: ties on created_at keep insert order

    def __init__(self, data_dir: Path) -> None:
        self.path = Path(data_dir) / DB_NAME
        self.location = str(self.path)
        self._lock = threading.RLock()
        self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None, timeout=10.0)
        self._db.row_factory = sqlite3.Row
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=NORMAL")  # WAL + NORMAL: durable across process kills

    def ensure_schema(self, table: Table) -> None:
        with self._lock:
            for statement in create_statements(table, TYPES):
                self._db.execute(statement)
            present = {row["name"] for row in self._db.execute(f"PRAGMA table_info({table.name})")}
            for name in table.added:
                if name not in present:
                    self._db.execute(f"ALTER TABLE {table.name} ADD COLUMN {column_sql(table.column(name), TYPES)}")
            for statement in index_statements(table):
                self._db.execute(statement)

    def execute(self, sql: str, params: Sequence[Any] = ()) -> int:
        """One statement in its own transaction; the number of rows it changed."""
        with self._lock:
            try:
                return self._db.execute(sql, tuple(params)).rowcount
            except sqlite3.IntegrityError as exc:
                if "UNIQUE" not in str(exc):
                    raise
                raise DuplicateKey(str(exc)) from exc

    def query(self, sql: str, params: Sequence[Any] = ()) -> list[dict[str, Any]]:
        """Every row at once: an UPDATE … RETURNING commits only once its rows are all read."""
        with self._lock:
            return [dict(row) for row in self._db.execute(sql, tuple(params)).fetchall()]

    def close(self) -> None:
        with self._lock:
            self._db.close()
