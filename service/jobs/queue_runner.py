"""How a worker's threads find work and keep it (a mixin of service.jobs.worker.JobWorker): each
of `concurrency` pool threads takes the store's next queued job (highest priority, then oldest)
until none is left; a lease thread renews this server's leases, stops live jobs whose lease
another server took over, and requeues (then runs) jobs whose lease lapsed because their server
died (service/jobs/leases.py).

It uses the worker's `store`, `_lock`, `_stopping`, `_pool`, `_concurrency`, `_draining`,
`_live`, `_lost` and `_run_guarded`, set up in JobWorker.__init__.
"""
from __future__ import annotations

import logging
import time
from typing import Callable

log = logging.getLogger("service.jobs.worker")  # one logger for the worker's messages


class LeaseLost(RuntimeError):
    """Another server took this job over (this one stalled past its lease): stop, write nothing."""


class QueueRunner:
    def _kick(self) -> None:
        """Bring the threads taking queued jobs up to `concurrency`; busy ones take the next job
        themselves when theirs ends."""
        with self._lock:
            if self._stopping.is_set():
                return
            missing = self._concurrency - self._draining
            self._draining += missing
        for _ in range(missing):
            try:
                self._pool.submit(self._drain)
            except RuntimeError:  # the pool shut down meanwhile: the server is stopping
                with self._lock:
                    self._draining -= 1

    def _drain(self) -> None:
        """Run the store's next queued job until none is left. A job another server claimed
        first is skipped (the claim in _run fails) and the next one tried."""
        try:
            while not self._stopping.is_set():
                job_id = self.store.next_queued()
                if job_id is None:
                    break
                self._run_guarded(job_id)
        except Exception:
            log.exception("taking the next queued job failed; the lease thread retries")
        finally:
            with self._lock:
                self._draining -= 1
        # A job queued between the empty look-up and the count above found every thread busy.
        if not self._stopping.is_set() and self._safe(self.store.next_queued) is not None:
            self._kick()

    # -- leases -------------------------------------------------------------------------------

    def _keep_leases(self) -> None:
        """Renew this server's leases; requeue and run jobs whose lease lapsed."""
        leases = self.store.leases
        next_sweep = time.monotonic() + leases.sweep_seconds
        while not self._stopping.wait(min(leases.renew_seconds, leases.sweep_seconds)):
            held = self._safe(self.store.renew_leases)
            if held is not None:
                self._mark_lost(set(held))
            if time.monotonic() < next_sweep:
                continue
            next_sweep = time.monotonic() + leases.sweep_seconds
            for job_id in self._safe(self.store.requeue_lapsed) or []:
                log.warning("job %s: its server's lease lapsed (the server is gone); requeued to resume "
                            "from its checkpoint", job_id)
            if self._safe(self.store.next_queued) is not None:
                self._kick()  # lapsed jobs, or ones a failed look-up left waiting

    def _mark_lost(self, held: set[str]) -> None:
        """A job rendering here whose lease is no longer ours (this server stalled past its
        lease and another resumed the job) stops at the next chunk and writes nothing more."""
        with self._lock:
            lost = [job_id for job_id in self._live if job_id not in held and job_id not in self._lost]
            self._lost.update(lost)
        for job_id in lost:
            log.error("job %s: this server lost its lease (stalled longer than a lease?); another server runs "
                      "it now, stopping here", job_id)

    def _lease_lost(self, job_id: str) -> bool:
        with self._lock:
            return job_id in self._lost

    @staticmethod
    def _safe(call: Callable):
        """A store call from a background thread: a database hiccup is logged, never fatal."""
        try:
            return call()
        except Exception:
            log.exception("job store call %s failed; retrying on the next round", getattr(call, "__name__", call))
            return None
