"""The one interface the API and the CLI talk to, whichever backend runs the jobs: `JobRunner`,
implemented by the thread backend (service.jobs.worker.JobWorker: loops in threads of the API
process) and the Ray backend (service.jobs.ray_worker.RayJobWorker: each job in Ray actors).
Neither subclasses the other; what both do the same way is in parts they each hold: the queue
and leases (service/jobs/queue_runner.py), λ edits (service/jobs/lambda_edits.py), previews
(service/jobs/previews.py), checkpoints (service/jobs/checkpoints.py), and the cancel flags and
the cancel/delete rules below."""
from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Callable, Protocol

import numpy as np

from service.jobs.artifacts import JobFiles, Preview
from service.jobs.errors import JobConflict
from service.jobs.lambda_edits import LambdaApplied, require
from service.jobs.record import JobRecord

DELETE_WAIT_SECONDS = 30.0  # a running job stops within one chunk; this bounds a stuck one


class WorkerObserver(Protocol):
    """Told what the runner did, for monitoring (service.api.metrics)."""

    def iteration_finished(self, timings: dict[str, float], samples: int) -> None:
        """One iteration: seconds per stage, samples it rendered over all frames."""

    def lambda_applied(self, seconds: float) -> None:
        """A λ edit, from its request to the preview version that shows it."""


class NoObserver:
    def iteration_finished(self, timings: dict[str, float], samples: int) -> None:
        pass

    def lambda_applied(self, seconds: float) -> None:
        pass


def add_timings(total: dict[str, float], more: dict[str, float]) -> dict[str, float]:
    """Seconds per stage, summed over iterations."""
    merged = dict(total)
    for stage, seconds in more.items():
        merged[stage] = merged.get(stage, 0.0) + float(seconds)
    return merged


def total_samples(buffers: list) -> int:
    """Samples accumulated in a job's frame buffers, all frames together."""
    return sum(int(buf.spp.sum()) for buf in buffers)


class JobRunner(Protocol):
    """Runs a store's queued jobs; what the routes and the app call."""

    def start(self) -> None:
        """Resume jobs whose server died, run queued ones."""

    def stop(self) -> None:
        """Running jobs stop within one wavefront chunk and stay resumable."""

    def submit(self, job_id: str) -> None:
        """A job was queued."""

    def cancel(self, job_id: str) -> JobRecord:
        """Cancel a queued or running job; JobConflict when it already finished."""

    def delete(self, job_id: str, wait_seconds: float = DELETE_WAIT_SECONDS) -> None:
        """Forget a job and its files, canceling it first."""

    def files(self, job_id: str) -> JobFiles:
        """The job's artifacts folder."""

    def image_size(self, job_id: str) -> tuple[int, int] | None:
        """(H, W) of the job's images, once known."""

    def current_lambda(self, job_id: str, shape: tuple[int, int]) -> np.ndarray:
        """The job's λ map (its saved one, else its global λ)."""

    def load_preview(self, job_id: str, frame: int) -> Preview | None:
        """The frame's newest preview, a λ edit's before its files are written."""

    def result_path(self, job_id: str, frame: int) -> Path:
        """The frame's result EXR, once the job's λ edits are written into it."""

    def set_lambda(self, job_id: str, lam: np.ndarray, value: float | None = None,
                   sequence: int | None = None) -> LambdaApplied:
        """Keep `lam` with the job and re-denoise; the preview version that shows it."""

    def health_problem(self) -> str | None:
        """Why no job can run here now, or None."""


class CancelFlags:
    """One flag per running job, set by a user's cancel; the job's loop checks it."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._flags: dict[str, threading.Event] = {}

    def flag(self, job_id: str) -> threading.Event:
        with self._lock:
            return self._flags.setdefault(job_id, threading.Event())

    def forget(self, job_id: str) -> None:
        with self._lock:
            self._flags.pop(job_id, None)


def cancel_job(store, flags: CancelFlags, job_id: str) -> tuple[JobRecord, bool]:
    """A queued job is canceled at once; a running one gets its flag set (its loop stops within
    one wavefront chunk). Returns the record and whether the job was running."""
    record = require(store, job_id)
    if record.finished:
        raise JobConflict(f"job {job_id} is already {record.state}")
    running = not store.cancel_if_queued(job_id)
    if running:
        flags.flag(job_id).set()
    return require(store, job_id), running


def stop_before_delete(runner: JobRunner, store, job_id: str, is_live: Callable[[str], bool],
                       wait_seconds: float) -> None:
    """Cancel an unfinished job and wait until it no longer runs here (JobConflict if it keeps
    running past `wait_seconds`); the caller then forgets it."""
    record = require(store, job_id)
    if record.finished:
        return
    runner.cancel(job_id)  # queued: at once; running: within one wavefront chunk
    deadline = time.monotonic() + wait_seconds
    while is_live(job_id) and time.monotonic() < deadline:
        time.sleep(0.05)
    if is_live(job_id):
        raise JobConflict(f"job {job_id} is still stopping; retry the delete in a moment")
