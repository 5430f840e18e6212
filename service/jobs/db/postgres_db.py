"""The job database on a PostgreSQL server (`serve --db postgresql://…`), for several servers.

Statements run in autocommit, one transaction each, so the store's conditional UPDATEs
(`… WHERE id = ? AND state = 'queued'`) are decided by PostgreSQL's row locks: of two
servers (or two threads) changing the same job, the second re-checks the condition on the
row the first committed and changes nothing. One connection per store behind a lock, as
with SQLite; the statements are tiny.
"""
from __future__ import annotations

import threading
from contextlib import contextmanager
from typing import Any, Iterator, Sequence

import psycopg
from psycopg import errors as pg_errors
from psycopg.rows import dict_row

from service.jobs.db.schema import DuplicateKey, Kind, Table, column_sql, create_statements, index_statements
from service.jobs.errors import StoreUnavailable

TYPES = {Kind.TEXT: "TEXT", Kind.INTEGER: "BIGINT", Kind.REAL: "DOUBLE PRECISION"}  # REAL would be 32-bit
# SQLite's rowid has no PostgreSQL twin: an identity column keeps the insertion order instead.
INSERTION_COLUMN = "seq BIGINT GENERATED ALWAYS AS IDENTITY"
# Servers starting at once would race on CREATE TABLE IF NOT EXISTS; a transaction-scoped
# advisory lock (any agreed number) lets one of them migrate at a time.
SCHEMA_LOCK_KEY = 0x72656E646572  # "render"
CONNECT_TIMEOUT_SECONDS = 10


def to_pyformat(sql: str) -> str:
    """The store writes SQLite's `?` placeholders; psycopg wants `%s` (and `%%` for a percent)."""
    if "%" in sql:
        raise ValueError(f"a literal % in job-store SQL needs escaping: {sql}")
    return sql.replace("?", "%s")


def one_line(exc: Exception) -> str:
    """libpq's messages span lines (a hint on the next); errors here are one line."""
    return " ".join(str(exc).split())


class PostgresDatabase:
    insertion_order = "seq"

    def __init__(self, url: str, location: str) -> None:
        self.url, self.location = url, location  # location: the URL without its password, for logs
        self._lock = threading.RLock()
        self._conn = self._connect()

    def _connect(self) -> psycopg.Connection:
        try:
            return psycopg.connect(self.url, autocommit=True, row_factory=dict_row,
                                   connect_timeout=CONNECT_TIMEOUT_SECONDS)
        except psycopg.OperationalError as exc:
            raise StoreUnavailable(f"cannot connect to PostgreSQL at {self.location}: {one_line(exc)}") from exc

    def _connection(self) -> psycopg.Connection:
        """The open connection; a new one when the server dropped the last (e.g. it restarted).
        Only before a statement is sent, so nothing is ever run twice."""
        if self._conn.closed or self._conn.broken:
            self._conn = self._connect()
        return self._conn

    def ensure_schema(self, table: Table) -> None:
        with self._lock:
            conn = self._connection()
            with conn.transaction():
                conn.execute("SELECT pg_advisory_xact_lock(%s)", (SCHEMA_LOCK_KEY,))
                for statement in create_statements(table, TYPES, (INSERTION_COLUMN,)):
                    conn.execute(statement)
                for name in table.added:
                    column = column_sql(table.column(name), TYPES)
                    conn.execute(f"ALTER TABLE {table.name} ADD COLUMN IF NOT EXISTS {column}")
                for statement in index_statements(table):
                    conn.execute(statement)

    def execute(self, sql: str, params: Sequence[Any] = ()) -> int:
        """One statement in its own transaction; the number of rows it changed."""
        with self._lock, self._reported():
            return self._connection().execute(to_pyformat(sql), tuple(params)).rowcount

    def query(self, sql: str, params: Sequence[Any] = ()) -> list[dict[str, Any]]:
        with self._lock, self._reported():
            return self._connection().execute(to_pyformat(sql), tuple(params)).fetchall()

    @contextmanager
    def _reported(self) -> Iterator[None]:
        """A lost server fails the statement in flight (it may or may not have committed, so it
        is not retried) as StoreUnavailable — a 503 — and the next statement reconnects."""
        try:
            yield
        except pg_errors.UniqueViolation as exc:
            raise DuplicateKey(one_line(exc)) from exc
        except psycopg.OperationalError as exc:
            raise StoreUnavailable(f"the job database at {self.location} failed: {one_line(exc)}") from exc

    def close(self) -> None:
        with self._lock:
            self._conn.close()
