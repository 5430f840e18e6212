"""Writes of a job's derived files off the request path, the newest per key winning.

A λ edit answers once its image is in memory; the files that follow from it (the preview layers,
a finished job's result EXRs: about a second at 2 MP) are written here, on one background thread.
A write waiting for its turn is replaced by a newer one for the same key (a slider dragged over
a finished job writes its last position's result, not every position's), so the queue holds at
most one write per key. `flush` waits for what was handed over before it was called: a graceful
stop, a GET of the result and the end of a job call it, so nothing answered with a 200 is lost
unless the process dies (the λ map itself is written before the answer: service.jobs.lambda_edits).
"""
from __future__ import annotations

import logging
import threading
from collections import OrderedDict
from typing import Callable, Hashable

log = logging.getLogger(__name__)


class LatestWriter:
    """One daemon thread; writes keyed by (job id, what), newest per key, in submission order."""

    def __init__(self, name: str = "latest-writer") -> None:
        self._name = name
        self._cond = threading.Condition()
        self._pending: OrderedDict[tuple[str, Hashable], Callable[[], None]] = OrderedDict()
        self._running: tuple[str, Hashable] | None = None
        self._thread: threading.Thread | None = None

    def submit(self, job_id: str, what: Hashable, write: Callable[[], None]) -> None:
        """Run `write` in the background; a not yet started write of the same (job, what) is dropped."""
        with self._cond:
            key = (job_id, what)
            self._pending.pop(key, None)
            self._pending[key] = write
            if self._thread is None:
                self._thread = threading.Thread(target=self._drain, name=self._name, daemon=True)
                self._thread.start()
            self._cond.notify_all()

    def flush(self, job_id: str | None = None, timeout: float | None = None) -> bool:
        """Wait until the job's (every job's, with None) writes have landed; False on timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: not self._busy(job_id), timeout)

    def discard(self, job_id: str) -> None:
        """Drop the job's waiting writes and wait for its running one (the job is being deleted)."""
        with self._cond:
            for key in [k for k in self._pending if k[0] == job_id]:
                del self._pending[key]
            self._cond.wait_for(lambda: not self._busy(job_id))

    def _busy(self, job_id: str | None) -> bool:
        keys = list(self._pending) + ([self._running] if self._running is not None else [])
        return any(job_id is None or key[0] == job_id for key in keys)

    def _drain(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: bool(self._pending))
                key, write = self._pending.popitem(last=False)
                self._running = key
            try:
                write()
            except Exception:  # noqa: BLE001 — the request was answered; the log is where this can go
                log.exception("job %s: writing its %s failed", key[0], key[1])
            finally:
                with self._cond:
                    self._running = None
                    self._cond.notify_all()
