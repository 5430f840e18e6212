"""Where job records live: the SQLite file in the data dir (default) or a PostgreSQL server
(`serve --db postgresql://…`). Each backend only connects, runs one statement at a time,
and migrates the schema; the store's logic is written once in service/jobs/store.py."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Protocol, Sequence
from urllib.parse import urlsplit, urlunsplit

from service.jobs.db.postgres_db import PostgresDatabase
from service.jobs.db.schema import Table
from service.jobs.db.sqlite_db import SqliteDatabase

POSTGRES_SCHEMES = ("postgresql", "postgres")


class Database(Protocol):
    """What the store needs from a database. SQL uses `?` placeholders and portable syntax
    (UPDATE … RETURNING included: SQLite ≥ 3.35 and PostgreSQL both have it)."""

    insertion_order: str  # a column that orders rows by insertion (ties on created_at)
    location: str  # for logs and errors: a path, or a URL without its password

    def ensure_schema(self, table: Table) -> None: ...
    def execute(self, sql: str, params: Sequence[Any] = ()) -> int: ...
    def query(self, sql: str, params: Sequence[Any] = ()) -> list[dict[str, Any]]: ...
    def close(self) -> None: ...


def is_postgres_url(url: str) -> bool:
    return urlsplit(url).scheme in POSTGRES_SCHEMES


def without_password(url: str) -> str:
    parts = urlsplit(url)
    if parts.password is None:
        return url
    host = parts.netloc.rsplit("@", 1)[1]
    return urlunsplit(parts._replace(netloc=f"{parts.username or ''}:***@{host}"))


def open_database(data_dir: Path, url: str | None = None) -> Database:
    """`url` None or empty: DATA/jobs.sqlite; otherwise a postgresql:// URL."""
    if not url:
        return SqliteDatabase(data_dir)
    if not is_postgres_url(url):
        raise ValueError(f"unsupported job database {without_password(url)!r}: give a postgresql:// URL")
    return PostgresDatabase(url, without_password(url))
