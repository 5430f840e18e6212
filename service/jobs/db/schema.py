"""The jobs table, once for every database: column names and portable kinds that each backend
maps to its own types (service/jobs/db/sqlite_db.py, postgres_db.py)."""
from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum


class Kind(StrEnum):
    """Portable column kinds. REAL means a 64-bit float: unix seconds need all of its digits."""

    TEXT = "text"
    INTEGER = "integer"
    REAL = "real"


@dataclass(frozen=True)
class Column:
    name: str
    kind: Kind
    constraint: str = ""  # e.g. "NOT NULL DEFAULT 0"; portable SQL only


@dataclass(frozen=True)
class Table:
    name: str
    key: str  # a TEXT primary key
    columns: tuple[Column, ...]  # every column but the key
    indexes: tuple[str, ...]  # indexed columns, one index each
    added: tuple[str, ...]  # columns added after the first release: migrated into old databases
    unique: tuple[tuple[str, ...], ...] = ()  # unique indexes over these columns (NULLs never clash)

    @property
    def column_names(self) -> tuple[str, ...]:
        return (self.key, *(c.name for c in self.columns))

    def column(self, name: str) -> Column:
        return next(c for c in self.columns if c.name == name)


JOBS = Table(
    name="jobs",
    key="id",
    columns=(
        Column("state", Kind.TEXT, "NOT NULL"),
        Column("spec", Kind.TEXT, "NOT NULL"),
        Column("iteration", Kind.INTEGER, "NOT NULL DEFAULT 0"),
        Column("spp", Kind.REAL, "NOT NULL DEFAULT 0"),
        Column("predicted_error", Kind.REAL),
        Column("stop_reason", Kind.TEXT),
        Column("timings", Kind.TEXT, "NOT NULL DEFAULT '{}'"),
        Column("error", Kind.TEXT),
        Column("created_at", Kind.REAL, "NOT NULL"),
        Column("started_at", Kind.REAL),
        Column("finished_at", Kind.REAL),
        Column("preview_version", Kind.INTEGER, "NOT NULL DEFAULT 0"),
        Column("lambda_value", Kind.REAL),
        Column("resumed_from", Kind.INTEGER),
        Column("effects", Kind.TEXT),
        Column("priority", Kind.INTEGER, "NOT NULL DEFAULT 0"),  # higher is claimed first
        Column("client", Kind.TEXT),  # who submitted: a token's digest or an address (quotas)
        Column("idempotency_key", Kind.TEXT),  # the submit's Idempotency-Key header, per client
        Column("lease_owner", Kind.TEXT),  # the server running the job (service/jobs/leases.py)
        Column("lease_expires_at", Kind.REAL),  # unix seconds; renewed while the job runs
        Column("eta_seconds", Kind.REAL),  # seconds left, as estimated after the last iteration (loop/eta.py)
        Column("eta_finish_at", Kind.REAL),  # unix seconds: when that estimate says the job ends
        Column("eta_basis", Kind.TEXT),  # what the estimate rests on, in words
        Column("stop_message", Kind.TEXT),  # stop_reason in words (loop/stop_message.py)
    ),
    indexes=("state",),
    added=("effects", "priority", "client", "idempotency_key", "lease_owner", "lease_expires_at",
           "eta_seconds", "eta_finish_at", "eta_basis", "stop_message"),
    unique=(("client", "idempotency_key"),),
)


class DuplicateKey(RuntimeError):
    """An insert clashed with a unique index (the same client's Idempotency-Key, twice)."""


def column_sql(column: Column, types: dict[Kind, str]) -> str:
    return f"{column.name} {types[column.kind]} {column.constraint}".rstrip()


def create_statements(table: Table, types: dict[Kind, str], extra_columns: tuple[str, ...] = ()) -> list[str]:
    """CREATE TABLE, idempotent; `extra_columns` are a backend's own (e.g. an insertion
    counter), written as full column definitions. Indexes come after the migration
    (index_statements): an old database gets the columns they index first."""
    columns = [f"{table.key} TEXT PRIMARY KEY", *(column_sql(c, types) for c in table.columns), *extra_columns]
    body = ",\n    ".join(columns)
    return [f"CREATE TABLE IF NOT EXISTS {table.name} (\n    {body}\n)"]


def index_statements(table: Table) -> list[str]:
    """CREATE [UNIQUE] INDEX, idempotent."""
    statements = [f"CREATE INDEX IF NOT EXISTS {table.name}_{name} ON {table.name}({name})" for name in table.indexes]
    for names in table.unique:
        statements.append(f"CREATE UNIQUE INDEX IF NOT EXISTS {table.name}_{'_'.join(names)}_key "
                          f"ON {table.name}({', '.join(names)})")
    return statements
