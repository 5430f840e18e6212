"""Opening the job database a URL names, and what the store needs from one."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Protocol, Sequence

from service.jobs.db.postgres_db import PostgresDatabase
from service.jobs.db.schema import Table
from service.jobs.db.sqlite_db import SqliteDatabase
from service.jobs.db.url import is_postgres_url, without_password


class Database(Protocol):
    """SQL uses `?` placeholders and portable syntax (UPDATE … RETURNING included: SQLite
    >= 3.35 and PostgreSQL both have it)."""

    insertion_order: str  # a column that orders rows by insertion (ties on created_at)
    location: str  # for logs and errors: a path, or a URL without its password

    def ensure_schema(self, table: Table) -> None: ...
    def execute(self, sql: str, params: Sequence[Any] = ()) -> int: ...
    def query(self, sql: str, params: Sequence[Any] = ()) -> list[dict[str, Any]]: ...
    def close(self) -> None: ...


def open_database(data_dir: Path, url: str | None = None) -> Database:
    """`url` None or empty: DATA/jobs.sqlite; otherwise a postgresql:// URL."""
    if not url:
        return SqliteDatabase(data_dir)
    if not is_postgres_url(url):
        raise ValueError(f"unsupported job database {without_password(url)!r}: give a postgresql:// URL")
    return PostgresDatabase(url, without_password(url))
