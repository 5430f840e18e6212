"""Housekeeping: finished jobs older than `keep_days` are removed, and while the data folder is
over `max_disk_bytes` the oldest finished jobs go first. Queued and running jobs are never
touched (serve --keep-days, --max-disk-gb). Their bundles count all the same: a submit that
finds the folder at its cap, after the finished jobs that may go are gone, is refused
(`check_room`, a 507), so queued uploads cannot grow the disk without bound.

Uploaded files are kept once (service/jobs/blobs.py): sizes count each inode once, as `du`
does, removing a job frees only the files no other job shares, and a blob goes with the last
job that links to it."""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from pathlib import Path

from service.jobs.blobs import BlobStore, freed_bytes, unique_bytes
from service.jobs.quotas import DiskFull
from service.jobs.store import TERMINAL_STATES, JobStore

SWEEP_SECONDS = 600.0  # how often a running server sweeps


@dataclass(frozen=True)
class Retention:
    keep_days: float | None = None  # None: keep finished jobs forever
    max_disk_bytes: float | None = None  # None: no cap on the data folder

    @property
    def active(self) -> bool:
        return self.keep_days is not None or self.max_disk_bytes is not None


def folder_bytes(folder: Path) -> int:
    """What the folder occupies, hard links counted once (twelve jobs of one bundle are one copy)."""
    return unique_bytes(folder)


def delete_jobs(store: JobStore, job_ids: list[str]) -> None:
    """Records, folders, and the blobs only these jobs used."""
    for job_id in job_ids:
        store.delete(job_id)
    if job_ids:
        BlobStore(store.data_dir).release_unused()


def sweep(store: JobStore, retention: Retention, now: float | None = None) -> list[str]:
    """Delete what the policy no longer keeps; returns the removed job ids, oldest first."""
    now = time.time() if now is None else now
    finished = [r for r in store.list(limit=2**31 - 1) if r.state in TERMINAL_STATES]
    finished.sort(key=lambda r: r.finished_at or r.created_at)  # oldest first
    removed = []
    if retention.keep_days is not None:
        cutoff = now - retention.keep_days * 86400.0
        expired = [r.id for r in finished if (r.finished_at or r.created_at) < cutoff]
        delete_jobs(store, expired)
        removed.extend(expired)
    if retention.max_disk_bytes is not None:
        remaining = [r for r in finished if r.id not in removed]
        used = folder_bytes(store.data_dir)
        while remaining and used > retention.max_disk_bytes:
            record = remaining.pop(0)
            used -= freed_bytes(store.job_dir(record.id))
            delete_jobs(store, [record.id])
            removed.append(record.id)
    return removed


def check_room(store: JobStore, retention: Retention) -> None:
    """DiskFull when the data folder (queued and running jobs' bundles and files included) is
    over `max_disk_bytes` even after sweeping what the policy lets go."""
    cap = retention.max_disk_bytes
    if cap is None or folder_bytes(store.data_dir) <= cap:
        return
    sweep(store, retention)
    used = folder_bytes(store.data_dir)
    if used > cap:
        raise DiskFull(f"the server's data folder is full ({used / 2**20:.1f} MiB of {cap / 2**20:.1f} MiB, "
                       "held by queued and running jobs); retry when some have finished")


class Housekeeper:
    """Sweeps once at start-up and then every SWEEP_SECONDS on a daemon thread."""

    def __init__(self, store: JobStore, retention: Retention, interval: float = SWEEP_SECONDS) -> None:
        self.store, self.retention, self.interval = store, retention, interval
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="housekeeper", daemon=True)

    def start(self) -> None:
        if self.retention.active:
            self._thread.start()

    def stop(self) -> None:
        self._stop.set()

    def _run(self) -> None:
        while True:
            sweep(self.store, self.retention)
            if self._stop.wait(self.interval):
                return
