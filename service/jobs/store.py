"""Job records in a database (the SQLite file `DATA/jobs.sqlite` by default, or PostgreSQL via
`serve --db postgresql://…`, see service/jobs/db/) and the per-job artifacts folder, which
stays on disk under the data dir whatever the database.

Crash safety: every state change is one conditional statement (`UPDATE … WHERE state = ?`,
`UPDATE … RETURNING`), never a read followed by a write, so a cancel and a worker claiming
the same job cannot both win, between threads and between server processes alike, and a
committed row survives `kill -9`.

Leases (service/jobs/leases.py): a claim writes this store's owner name and an expiry; the
owner renews it while the job runs, and any store requeues a running job whose lease lapsed.
Quotas (service/jobs/quotas.py) are checked in `create`, next to the insert they guard.
"""
from __future__ import annotations

import json
import shutil
import threading
import time
import uuid
from pathlib import Path
from typing import Any

from service.jobs.db.connect import Database, open_database
from service.jobs.db.schema import JOBS, DuplicateKey
from service.jobs.leases import Leases, new_owner, owner_is_gone
from service.jobs.quotas import QuotaExceeded, Quotas
# The record and its states live in service/jobs/record.py; imported from here too, as before.
from service.jobs.record import (CANCELED, CANCELED_WHILE_QUEUED, COMPLETED, FAILED, QUEUED, RUNNING,  # noqa: F401
                                 STATES, TERMINAL_STATES, JobRecord, JobState)
from service.loop.eta import Progress


class AlreadySubmitted(RuntimeError):
    """The client sent this Idempotency-Key before: `record` is the job that submit created."""

    def __init__(self, record: JobRecord) -> None:
        super().__init__(f"job {record.id} was already submitted with this Idempotency-Key")
        self.record = record


class JobStore:
    """Thread-safe access to the jobs table plus the artifacts layout under `data_dir`."""

    def __init__(self, data_dir: Path, db_url: str | None = None, leases: Leases = Leases()) -> None:
        """`db_url` None: the SQLite file in `data_dir`; a postgresql:// URL: that database."""
        # absolute from here on: `serve --data-dir data` (make run) is relative to the server's cwd,
        # and the bundle and sandbox checks compare resolved paths
        self.data_dir = Path(data_dir).resolve()
        self.jobs_dir = self.data_dir / "jobs"
        self.jobs_dir.mkdir(parents=True, exist_ok=True)
        self._db: Database = open_database(self.data_dir, db_url)
        self._db.ensure_schema(JOBS)
        self._order = self._db.insertion_order
        self.leases = leases
        self.owner = new_owner()  # this store's name on the jobs it claims
        # Submits in this process check the queue and insert one at a time, so two of them
        # cannot both take the last place (between servers a cap may overshoot by one per server).
        self._admission = threading.Lock()

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

    def create(self, spec: dict[str, Any], lambda_value: float | None, job_id: str | None = None, *,
               client: str | None = None, idempotency_key: str | None = None,
               quotas: Quotas | None = None) -> JobRecord:
        """A queued job. With `quotas`, refused (QuotaExceeded) when the queue is full for
        everyone or for `client`; a repeated (client, idempotency_key) raises AlreadySubmitted
        with the first job, before any quota counts."""
        job_id = job_id or uuid.uuid4().hex
        with self._admission:
            self._check_repeat(client, idempotency_key)
            if quotas is not None:
                self.check_queue(client, quotas)
            try:
                self._db.execute(
                    "INSERT INTO jobs (id, state, spec, created_at, lambda_value, priority, client, idempotency_key) "
                    "VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                    (job_id, QUEUED, json.dumps(spec), time.time(), lambda_value, int(spec.get("priority", 0)),
                     client, idempotency_key),
                )
            except DuplicateKey:
                self._check_repeat(client, idempotency_key)  # another server inserted it first
                raise
        self.job_dir(job_id).mkdir(parents=True, exist_ok=True)
        record = self.get(job_id)
        assert record is not None
        return record

    def find_submitted(self, client: str | None, idempotency_key: str | None) -> JobRecord | None:
        """The job this client created with this Idempotency-Key, if any."""
        if idempotency_key is None:
            return None
        if client is None:
            records = self._select("WHERE client IS NULL AND idempotency_key = ?", (idempotency_key,))
        else:
            records = self._select("WHERE client = ? AND idempotency_key = ?", (client, idempotency_key))
        return records[0] if records else None

    def _check_repeat(self, client: str | None, idempotency_key: str | None) -> None:
        first = self.find_submitted(client, idempotency_key)
        if first is not None:
            raise AlreadySubmitted(first)

    def count_queued(self, client: str | None = None) -> int:
        where, params = ("state = ? AND client = ?", (QUEUED, client)) if client else ("state = ?", (QUEUED,))
        return int(self._db.query(f"SELECT COUNT(*) AS n FROM jobs WHERE {where}", params)[0]["n"])

    def check_queue(self, client: str | None, quotas: Quotas) -> None:
        """QuotaExceeded when no more jobs may wait, in all or for `client`."""
        queued = self.count_queued()
        if queued >= quotas.max_queued:
            raise QuotaExceeded(f"the server's queue is full ({queued} jobs waiting, cap {quotas.max_queued}); "
                                f"retry later", quotas.retry_after_seconds)
        if client is not None:
            mine = self.count_queued(client)
            if mine >= quotas.max_queued_per_client:
                raise QuotaExceeded(f"you have {mine} jobs waiting, the cap per client is "
                                    f"{quotas.max_queued_per_client}; retry when one has started",
                                    quotas.retry_after_seconds)

    @staticmethod
    def new_id() -> str:
        return uuid.uuid4().hex

    def claim(self, job_id: str) -> bool:
        """queued → running under this store's lease; False when someone else got there first
        (e.g. a cancel, another server)."""
        now = time.time()
        return self._db.execute(
            "UPDATE jobs SET state = ?, started_at = COALESCE(started_at, ?), lease_owner = ?, lease_expires_at = ? "
            "WHERE id = ? AND state = ?",
            (RUNNING, now, self.owner, now + self.leases.seconds, job_id, QUEUED),
        ) == 1

    def next_queued(self) -> str | None:
        """The queued job to claim next: highest priority, then oldest."""
        rows = self._db.query(f"SELECT id FROM jobs WHERE state = ? ORDER BY priority DESC, created_at, "
                              f"{self._order} LIMIT 1", (QUEUED,))
        return rows[0]["id"] if rows else None

    def renew_leases(self) -> list[str]:
        """Extend the lease of every job this store runs; the ids it still holds."""
        rows = self._db.query(
            "UPDATE jobs SET lease_expires_at = ? WHERE state = ? AND lease_owner = ? RETURNING id",
            (time.time() + self.leases.seconds, RUNNING, self.owner),
        )
        return [r["id"] for r in rows]

    def renew_lease(self, job_id: str) -> bool:
        """Extend one job's lease; False when this store no longer holds it (another server took
        the job over): the caller must not write the job's files or record any more."""
        return self._db.execute(
            "UPDATE jobs SET lease_expires_at = ? WHERE id = ? AND state = ? AND lease_owner = ?",
            (time.time() + self.leases.seconds, job_id, RUNNING, self.owner),
        ) == 1

    def requeue_lapsed(self) -> list[str]:
        """running → queued for every job whose lease lapsed (its server is gone), oldest first.
        A job without a lease was claimed by a server from before leases: it counts as lapsed."""
        rows = self._db.query(
            "UPDATE jobs SET state = ?, lease_owner = NULL, lease_expires_at = NULL "
            "WHERE state = ? AND (lease_expires_at IS NULL OR lease_expires_at < ?) RETURNING id, created_at",
            (QUEUED, RUNNING, time.time()),
        )
        return [r["id"] for r in sorted(rows, key=lambda r: r["created_at"])]

    def requeue_abandoned(self) -> list[str]:
        """At start-up: the lapsed jobs, and those whose owner was a process on this host that is
        gone (this server's previous life: no need to wait for its lease). A live other server's
        jobs stay running."""
        requeued = self.requeue_lapsed()
        rows = self._db.query("SELECT id, lease_owner, created_at FROM jobs WHERE state = ?", (RUNNING,))
        for row in sorted(rows, key=lambda r: r["created_at"]):
            if owner_is_gone(row["lease_owner"]) and self._db.execute(
                    "UPDATE jobs SET state = ?, lease_owner = NULL, lease_expires_at = NULL "
                    "WHERE id = ? AND state = ? AND lease_owner = ?", (QUEUED, row["id"], RUNNING, row["lease_owner"])):
                requeued.append(row["id"])
        return requeued

    def record_iteration(
        self,
        job_id: str,
        iteration: int,
        spp: float,
        predicted_error: float | None,
        timings: dict[str, float],
        stop_reason: str | None = None,
        progress: Progress | None = None,
    ) -> None:
        """One finished iteration; `progress` (the ETA, the stop message) when the worker has it."""
        eta = progress.eta if progress is not None else None
        seconds = eta.seconds if eta is not None else None
        finish_at = time.time() + seconds if seconds is not None else None
        self._db.execute(
            "UPDATE jobs SET iteration = ?, spp = ?, predicted_error = ?, timings = ?, "
            "stop_reason = COALESCE(?, stop_reason), eta_seconds = ?, eta_finish_at = ?, "
            "eta_basis = ?, stop_message = COALESCE(?, stop_message) WHERE id = ?",
            (iteration, spp, predicted_error, json.dumps(timings), stop_reason, seconds, finish_at,
             eta.basis if eta is not None else None, progress.stop_message if progress is not None else None,
             job_id),
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

    def finish(self, job_id: str, state: str, stop_reason: str | None = None, error: str | None = None,
               stop_message: str | None = None) -> None:
        if state not in TERMINAL_STATES:
            raise ValueError(f"{state!r} is not a terminal state")
        # Not over a job another server took over (this one stalled past its lease): theirs to end.
        self._db.execute(
            "UPDATE jobs SET state = ?, stop_reason = COALESCE(?, stop_reason), error = ?, finished_at = ?, "
            "stop_message = COALESCE(?, stop_message) WHERE id = ? AND (lease_owner = ? OR lease_owner IS NULL)",
            (state, stop_reason, error, time.time(), stop_message, job_id, self.owner),
        )

    def delete(self, job_id: str) -> None:
        """The record and the job's folder; the caller makes sure nothing renders it any more."""
        self._db.execute("DELETE FROM jobs WHERE id = ?", (job_id,))
        shutil.rmtree(self.job_dir(job_id), ignore_errors=True)

    def cancel_if_queued(self, job_id: str) -> bool:
        return self._db.execute(
            "UPDATE jobs SET state = ?, stop_reason = 'canceled', stop_message = ?, finished_at = ? "
            "WHERE id = ? AND state = ?",
            (CANCELED, CANCELED_WHILE_QUEUED, time.time(), job_id, QUEUED),
        ) == 1

    def requeue(self, job_id: str) -> None:
        """running → queued: the job resumes from its checkpoint when a worker picks it up. Only
        while this store holds its lease: a job another server took over stays theirs."""
        self._db.execute(
            "UPDATE jobs SET state = ?, lease_owner = NULL, lease_expires_at = NULL "
            "WHERE id = ? AND state = ? AND (lease_owner = ? OR lease_owner IS NULL)",
            (QUEUED, job_id, RUNNING, self.owner),
        )

    def requeue_running(self) -> list[str]:
        """Every running job back in line, whoever runs it: only right when this is the one
        server on the database (the worker uses requeue_abandoned). One statement, so a job
        that finishes meanwhile is not dragged back to queued."""
        rows = self._db.query(
            "UPDATE jobs SET state = ?, lease_owner = NULL, lease_expires_at = NULL WHERE state = ? "
            "RETURNING id, created_at", (QUEUED, RUNNING)
        )
        return [r["id"] for r in sorted(rows, key=lambda r: r["created_at"])]


_COLUMNS = ", ".join(JOBS.column_names)
