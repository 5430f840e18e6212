"""What POST /jobs checks before a job joins the queue (service.jobs.quotas): who submits it, its
Idempotency-Key, the queue caps and the disk cap, each refusal as the HTTP error it is."""
from __future__ import annotations

import shutil

from fastapi import HTTPException, Request

from service.api.submit import invalid
from service.jobs.quotas import DiskFull, QuotaExceeded, check_idempotency_key, client_key
from service.jobs.retention import Retention, check_room
from service.jobs.store import AlreadySubmitted, JobRecord, JobStore

IDEMPOTENCY_HEADER = "idempotency-key"


def submitter(request: Request) -> str:
    """The client a submit counts against: its bearer token (header or `?token=`), else its
    address."""
    auth = request.headers.get("authorization", "")
    token = auth[7:].strip() if auth[:7].lower() == "bearer " else request.query_params.get("token")
    return client_key(token or None, request.client.host if request.client else None)


def idempotency_key(request: Request) -> str | None:
    value = request.headers.get(IDEMPOTENCY_HEADER)
    if value is None:
        return None
    try:
        return check_idempotency_key(value)
    except ValueError as exc:
        raise invalid("Idempotency-Key", str(exc)) from exc


def too_many(exc: QuotaExceeded) -> HTTPException:
    return HTTPException(429, str(exc), headers={"Retry-After": str(exc.retry_after)})


def disk_full(exc: DiskFull) -> HTTPException:
    return HTTPException(507, str(exc))


def admit(store: JobStore, request: Request, client: str) -> None:
    """Refuse early, before an upload is unpacked: a full queue (429) or a full disk (507)."""
    try:
        store.check_queue(client, request.app.state.quotas)
        check_room(store, retention_of(request))
    except QuotaExceeded as exc:
        raise too_many(exc) from exc
    except DiskFull as exc:
        raise disk_full(exc) from exc


def check_disk(store: JobStore, request: Request) -> None:
    """After an upload is unpacked: the data folder, with it, still under the disk cap (507)."""
    try:
        check_room(store, retention_of(request))
    except DiskFull as exc:
        raise disk_full(exc) from exc


def retention_of(request: Request) -> Retention:
    return getattr(request.app.state, "retention", Retention())


def create_job(store: JobStore, request: Request, spec: dict, lam: float, client: str, key: str | None,
               job_id: str | None = None) -> tuple[JobRecord, bool]:
    """The new queued job and True, or the job this client's Idempotency-Key already made and
    False; a refusal removes the unpacked bundle of `job_id` (an upload)."""
    try:
        return store.create(spec, lam, job_id=job_id, client=client, idempotency_key=key,
                            quotas=request.app.state.quotas), True
    except AlreadySubmitted as repeat:
        discard(store, job_id)
        return repeat.record, False
    except QuotaExceeded as exc:
        discard(store, job_id)
        raise too_many(exc) from exc


def discard(store: JobStore, job_id: str | None) -> None:
    if job_id is not None:
        shutil.rmtree(store.job_dir(job_id), ignore_errors=True)
