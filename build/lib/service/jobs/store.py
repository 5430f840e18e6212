"""Job records in one SQLite file (`DATA/jobs.sqlite`) and the per-job artifacts folder.

SQLite in WAL mode lets the HTTP handlers read while a worker thread writes, and it survives
`kill -9`: a committed row is on disk. State changes are single conditional UPDATEs so a
cancel and a worker claiming the same job cannot both win.
"""
from __future__ import annotations

import json
import shutil
import sqlite3
import threading
import time
import uuid
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any


class JobState(StrEnum):
    """A job's life: queued → running → one of the three terminal states (stored as text)."""

    QUEUED = "queued"
    RUNNING = "running"
    COMPLETED = "completed"
    FAILED = "failed"
    CANCELED = "canceled"


QUEUED, RUNNING, COMPLETED, FAILED, CANCELED = JobState
STATES = tuple(state.value for state in JobState)
TERMINAL_STATES = frozenset({COMPLETED, FAILED, CANCELED})
DB_NAME = "jobs.sqlite"

_SCHEMA = """
CREATE TABLE IF NOT EXISTS jobs (
    id              TEXT PRIMARY KEY,
    state           TEXT NOT NULL,
    spec            TEXT NOT NULL,
    iteration       INTEGER NOT NULL DEFAULT 0,
    spp             REAL NOT NULL DEFAULT 0,
    predicted_error REAL,
    stop_reason     TEXT,
    timings         TEXT NOT NULL DEFAULT '{}',
    error           TEXT,
    created_at      REAL NOT NULL,
    started_at      REAL,
    finished_at     REAL,
    preview_version INTEGER NOT NULL DEFAULT 0,
    lambda_value    REAL,
    resumed_from    INTEGER,
    effects         TEXT
);
CREATE INDEX IF NOT EXISTS jobs_state ON jobs(state);
"""
# Columns added after the first release, for data folders made before them.
_ADDED_COLUMNS = {"effects": "TEXT"}


@dataclass
class JobRecord:
    """One row of the jobs table, decoded."""

    id: str
    state: str
    spec: dict[str, Any]
    iteration: int = 0  # finished iterations
    spp: float = 0.0  # mean samples per pixel so far
    predicted_error: float | None = None
    stop_reason: str | None = None
    timings: dict[str, float] = field(default_factory=dict)  # seconds per stage, summed
    error: str | None = None
    created_at: float = 0.0  # unix seconds
    started_at: float | None = None
    finished_at: float | None = None
    preview_version: int = 0
    lambda_value: float | None = None  # the global λ last set; None once a per-pixel map is set
    resumed_from: int | None = None  # iteration the last restart resumed at; None if never resumed
    effects: dict[str, Any] | None = None  # the effects report once the scene is loaded

    @property
    def finished(self) -> bool:
        return self.state in TERMINAL_STATES

    @classmethod
    def from_row(cls, row: sqlite3.Row) -> "JobRecord":
        values = dict(row)
        values["spec"] = json.loads(values["spec"])
        values["timings"] = json.loads(values["timings"])
        values["effects"] = json.loads(values["effects"]) if values.get("effects") else None
        return cls(**values)


class JobStore:
    """Thread-safe access to the jobs table plus the artifacts layout under `data_dir`."""

    def __init__(self, data_dir: Path) -> None:
        self.data_dir = Path(data_dir)
        self.jobs_dir = self.data_dir / "jobs"
        self.jobs_dir.mkdir(parents=True, exist_ok=True)
        # One connection shared by all threads behind a lock: the statements are tiny, and a
        # single writer sidesteps SQLITE_BUSY between our own threads.
        self._lock = threading.RLock()
        self._db = sqlite3.connect(
            self.data_dir / DB_NAME, check_same_thread=False, isolation_level=None, timeout=10.0
        )
        self._db.row_factory = sqlite3.Row
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=NORMAL")  # WAL + NORMAL: durable across process kills
        self._db.executescript(_SCHEMA)
        present = {row["name"] for row in self._db.execute("PRAGMA table_info(jobs)")}
        for column, kind in _ADDED_COLUMNS.items():
            if column not in present:
                self._db.execute(f"ALTER TABLE jobs ADD COLUMN {column} {kind}")

    def close(self) -> None:
        with self._lock:
            self._db.close()

    def job_dir(self, job_id: str) -> Path:
        return self.jobs_dir / job_id

    def _execute(self, sql: str, params: tuple = ()) -> sqlite3.Cursor:
        with self._lock:
            return self._db.execute(sql, params)

    # -- reads ------------------------------------------------------------------------------

    def get(self, job_id: str) -> JobRecord | None:
        row = self._execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return JobRecord.from_row(row) if row else None

    def list(self, state: str | None = None, limit: int = 100, offset: int = 0) -> list[JobRecord]:
        where, params = ("WHERE state = ?", (state,)) if state else ("", ())
        rows = self._execute(
            f"SELECT * FROM jobs {where} ORDER BY created_at DESC, rowid DESC LIMIT ? OFFSET ?",
            (*params, limit, offset),
        ).fetchall()
        return [JobRecord.from_row(r) for r in rows]

    def ids_in_state(self, state: str) -> list[str]:
        rows = self._execute(
            "SELECT id FROM jobs WHERE state = ? ORDER BY created_at, rowid", (state,)
        ).fetchall()
        return [r["id"] for r in rows]

    # -- writes -----------------------------------------------------------------------------

    def create(self, spec: dict[str, Any], lambda_value: float | None, job_id: str | None = None) -> JobRecord:
        job_id = job_id or uuid.uuid4().hex
        self._execute(
            "INSERT INTO jobs (id, state, spec, created_at, lambda_value) VALUES (?, ?, ?, ?, ?)",
            (job_id, QUEUED, json.dumps(spec), time.time(), lambda_value),
        )
        self.job_dir(job_id).mkdir(parents=True, exist_ok=True)
        record = self.get(job_id)
        assert record is not None
        return record

    @staticmethod
    def new_id() -> str:
        return uuid.uuid4().hex

    def claim(self, job_id: str) -> bool:
        """queued → running; False when someone else got there first (e.g. a cancel)."""
        cursor = self._execute(
            "UPDATE jobs SET state = ?, started_at = COALESCE(started_at, ?) WHERE id = ? AND state = ?",
            (RUNNING, time.time(), job_id, QUEUED),
        )
        return cursor.rowcount == 1

    def record_iteration(
        self,
        job_id: str,
        iteration: int,
        spp: float,
        predicted_error: float | None,
        timings: dict[str, float],
        stop_reason: str | None = None,
    ) -> None:
        self._execute(
            "UPDATE jobs SET iteration = ?, spp = ?, predicted_error = ?, timings = ?, "
            "stop_reason = COALESCE(?, stop_reason) WHERE id = ?",
            (iteration, spp, predicted_error, json.dumps(timings), stop_reason, job_id),
        )

    def bump_preview_version(self, job_id: str) -> int:
        with self._lock:
            self._db.execute(
                "UPDATE jobs SET preview_version = preview_version + 1 WHERE id = ?", (job_id,)
            )
            row = self._db.execute("SELECT preview_version FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return int(row["preview_version"])

    def set_effects(self, job_id: str, effects: dict[str, Any]) -> None:
        self._execute("UPDATE jobs SET effects = ? WHERE id = ?", (json.dumps(effects), job_id))

    def set_resumed_from(self, job_id: str, iteration: int) -> None:
        self._execute("UPDATE jobs SET resumed_from = ? WHERE id = ?", (iteration, job_id))

    def set_lambda_value(self, job_id: str, value: float | None) -> None:
        self._execute("UPDATE jobs SET lambda_value = ? WHERE id = ?", (value, job_id))

    def finish(self, job_id: str, state: str, stop_reason: str | None = None, error: str | None = None) -> None:
        if state not in TERMINAL_STATES:
            raise ValueError(f"{state!r} is not a terminal state")
        self._execute(
            "UPDATE jobs SET state = ?, stop_reason = COALESCE(?, stop_reason), error = ?, finished_at = ? "
            "WHERE id = ?",
            (state, stop_reason, error, time.time(), job_id),
        )

    def delete(self, job_id: str) -> None:
        """The record and the job's folder; the caller makes sure nothing renders it any more."""
        self._execute("DELETE FROM jobs WHERE id = ?", (job_id,))
        shutil.rmtree(self.job_dir(job_id), ignore_errors=True)

    def cancel_if_queued(self, job_id: str) -> bool:
        cursor = self._execute(
            "UPDATE jobs SET state = ?, stop_reason = 'canceled', finished_at = ? WHERE id = ? AND state = ?",
            (CANCELED, time.time(), job_id, QUEUED),
        )
        return cursor.rowcount == 1

    def requeue(self, job_id: str) -> None:
        """running → queued: the job resumes from its checkpoint when a worker picks it up."""
        self._execute("UPDATE jobs SET state = ? WHERE id = ? AND state = ?", (QUEUED, job_id, RUNNING))

    def requeue_running(self) -> list[str]:
        """After a crash or restart nothing is running any more: put those jobs back in line."""
        ids = self.ids_in_state(RUNNING)
        for job_id in ids:
            self.requeue(job_id)
        return ids
