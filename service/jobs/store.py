"""Job records in a database (the SQLite file `DATA/jobs.sqlite` by default, or PostgreSQL via
`serve --db postgresql://…`, see service/jobs/db/) and the per-job artifacts folder, which
stays on disk under the data dir whatever the database.

Crash safety: every state change is one conditional statement (`UPDATE … WHERE state = ?`,
`UPDATE … RETURNING`), never a read followed by a write, so a cancel and a worker claiming
the same job cannot both win, between threads and between server processes alike, and a
committed row survives `kill -9`.
"""
from __future__ import annotations

import json
import shutil
import time
import uuid
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any

from service.jobs.db.connect import Database, open_database
from service.jobs.db.schema import JOBS


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
    def from_row(cls, row: dict[str, Any]) -> "JobRecord":
        values = dict(row)
        values["spec"] = json.loads(values["spec"])
        values["timings"] = json.loads(values["timings"])
        values["effects"] = json.loads(values["effects"]) if values.get("effects") else None
        return cls(**values)


class JobStore:
    """Thread-safe access to the jobs table plus the artifacts layout under `data_dir`."""

    def __init__(self, data_dir: Path, db_url: str | None = None) -> None:
        """`db_url` None: the SQLite file in `data_dir`; a postgresql:// URL: that database."""
        # absolute from here on: `serve --data-dir data` (make run) is relative to the server's cwd,
        # and the bundle and sandbox checks compare resolved paths
        self.data_dir = Path(data_dir).resolve()
        self.jobs_dir = self.data_dir / "jobs"
        self.jobs_dir.mkdir(parents=True, exist_ok=True)
        self._db: Database = open_database(self.data_dir, db_url)
        self._db.ensure_schema(JOBS)
        self._order = self._db.insertion_order

    def close(self) -> None:
        self._db.close()

    def job_dir(self, job_id: str) -> Path:
        return self.jobs_dir / job_id

    def _select(self, tail: str, params: tuple = ()) -> list[JobRecord]:
        # Named columns, not `*`: a backend's own columns (PostgreSQL's seq) stay out of records.
        rows = self._db.query(f"SELECT {_COLUMNS} FROM jobs {tail}", params)
        return [JobRecord.from_row(row) for row in rows]

    # -- reads ------------------------------------------------------------------------------

    def get(self, job_id: str) -> JobRecord | None:
        records = self._select("WHERE id = ?", (job_id,))
        return records[0] if records else None

    def list(self, state: str | None = None, limit: int = 100, offset: int = 0) -> list[JobRecord]:
        where, params = ("WHERE state = ?", (state,)) if state else ("", ())
        return self._select(f"{where} ORDER BY created_at DESC, {self._order} DESC LIMIT ? OFFSET ?",
                            (*params, limit, offset))

    def ids_in_state(self, state: str) -> list[str]:
        rows = self._db.query(f"SELECT id FROM jobs WHERE state = ? ORDER BY created_at, {self._order}",
                              (state,))
        return [r["id"] for r in rows]

    # -- writes -----------------------------------------------------------------------------

    def create(self, spec: dict[str, Any], lambda_value: float | None, job_id: str | None = None) -> JobRecord:
        job_id = job_id or uuid.uuid4().hex
        self._db.execute(
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
        return self._db.execute(
            "UPDATE jobs SET state = ?, started_at = COALESCE(started_at, ?) WHERE id = ? AND state = ?",
            (RUNNING, time.time(), job_id, QUEUED),
        ) == 1

    def record_iteration(
        self,
        job_id: str,
        iteration: int,
        spp: float,
        predicted_error: float | None,
        timings: dict[str, float],
        stop_reason: str | None = None,
    ) -> None:
        self._db.execute(
            "UPDATE jobs SET iteration = ?, spp = ?, predicted_error = ?, timings = ?, "
            "stop_reason = COALESCE(?, stop_reason) WHERE id = ?",
            (iteration, spp, predicted_error, json.dumps(timings), stop_reason, job_id),
        )

    def bump_preview_version(self, job_id: str) -> int:
        rows = self._db.query(
            "UPDATE jobs SET preview_version = preview_version + 1 WHERE id = ? RETURNING preview_version",
            (job_id,),
        )
        return int(rows[0]["preview_version"])

    def set_effects(self, job_id: str, effects: dict[str, Any]) -> None:
        self._db.execute("UPDATE jobs SET effects = ? WHERE id = ?", (json.dumps(effects), job_id))

    def set_resumed_from(self, job_id: str, iteration: int) -> None:
        self._db.execute("UPDATE jobs SET resumed_from = ? WHERE id = ?", (iteration, job_id))

    def set_lambda_value(self, job_id: str, value: float | None) -> None:
        self._db.execute("UPDATE jobs SET lambda_value = ? WHERE id = ?", (value, job_id))

    def finish(self, job_id: str, state: str, stop_reason: str | None = None, error: str | None = None) -> None:
        if state not in TERMINAL_STATES:
            raise ValueError(f"{state!r} is not a terminal state")
        self._db.execute(
            "UPDATE jobs SET state = ?, stop_reason = COALESCE(?, stop_reason), error = ?, finished_at = ? "
            "WHERE id = ?",
            (state, stop_reason, error, time.time(), job_id),
        )

    def delete(self, job_id: str) -> None:
        """The record and the job's folder; the caller makes sure nothing renders it any more."""
        self._db.execute("DELETE FROM jobs WHERE id = ?", (job_id,))
        shutil.rmtree(self.job_dir(job_id), ignore_errors=True)

    def cancel_if_queued(self, job_id: str) -> bool:
        return self._db.execute(
            "UPDATE jobs SET state = ?, stop_reason = 'canceled', finished_at = ? WHERE id = ? AND state = ?",
            (CANCELED, time.time(), job_id, QUEUED),
        ) == 1

    def requeue(self, job_id: str) -> None:
        """running → queued: the job resumes from its checkpoint when a worker picks it up."""
        self._db.execute("UPDATE jobs SET state = ? WHERE id = ? AND state = ?", (QUEUED, job_id, RUNNING))

    def requeue_running(self) -> list[str]:
        """After a crash or restart nothing is running any more: put those jobs back in line.
        One statement, so a job that finishes meanwhile is not dragged back to queued."""
        rows = self._db.query(
            "UPDATE jobs SET state = ? WHERE state = ? RETURNING id, created_at", (QUEUED, RUNNING)
        )
        return [r["id"] for r in sorted(rows, key=lambda r: r["created_at"])]


_COLUMNS = ", ".join(JOBS.column_names)
