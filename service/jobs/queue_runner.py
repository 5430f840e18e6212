"""How a backend's threads find work and keep it (held by both JobRunner implementations): each
of `concurrency` pool threads takes the store's next queued job (highest priority, then oldest)
until none is left and hands it to the backend's `run`; a job whose run raised fails with the
message. A lease thread renews this server's leases, marks live jobs whose lease another server
took over as lost, and requeues (then runs) jobs whose lease lapsed because their server died
(service/jobs/leases.py).
"""
from __future__ import annotations

import logging
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Iterable

from service.jobs.record import FAILED

log = logging.getLogger("service.jobs.worker")  # one logger for the worker's messages


class LeaseLost(RuntimeError):
    """Another server took this job over (this one stalled past its lease): stop, write nothing."""


def failure_message(exc: BaseException) -> str:
    """What a failed job's record says."""
    text = str(exc).strip() or exc.__class__.__name__
    return f"{exc.__class__.__name__}: {text}" if not isinstance(exc, ValueError) else text


class QueueRunner:
    """`run(job_id)` claims one job and runs it to its end; it returns False when it did not
    claim it (another thread or server did first, or the server is stopping). `ended(job_id)`
    is told once a run that claimed its job returned or raised — never for one that did not:
    two threads can pick the same queued job, and the one that lost the claim must not clear
    the winner's cancel flag. `live()` names the jobs rendering here (the lease thread stops
    those another server took over)."""

    def __init__(self, store, concurrency: int, run: Callable[[str], bool], ended: Callable[[str], None],
                 live: Callable[[], Iterable[str]], stopping: threading.Event) -> None:
        if concurrency < 1:
            raise ValueError("concurrency must be >= 1")
        self.store = store
        self._run, self._ended, self._live = run, ended, live
        self._stopping = stopping
        self._concurrency = concurrency
        self._pool = ThreadPoolExecutor(max_workers=concurrency, thread_name_prefix="render")
        self._lock = threading.Lock()
        self._draining = 0  # pool tasks taking queued jobs (at most `concurrency`)
        self._lost: set[str] = set()  # live jobs whose lease another server took over
        self._leases = threading.Thread(target=self._keep_leases, name="leases", daemon=True)

    def start(self) -> None:
        """Jobs whose server died (this one's last life, or another whose lease lapsed) resume;
        queued ones run. A live other server's running jobs stay its own."""
        for job_id in self.store.requeue_abandoned():
            log.info("job %s was running on a server that is gone: resuming from its checkpoint", job_id)
        self._leases.start()
        self.kick()

    def stop(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)

    def kick(self) -> None:
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

    def lease_lost(self, job_id: str) -> bool:
        with self._lock:
            return job_id in self._lost

    def hold_lease(self, job_id: str) -> None:
        """Before a checkpoint: the job must still be this server's; else another server resumed
        it, and nothing here may write its files or record any more (LeaseLost)."""
        if not self.store.renew_lease(job_id):
            with self._lock:
                self._lost.add(job_id)
            raise LeaseLost(job_id)

    def _drain(self) -> None:
        """Run the store's next queued job until none is left. A job another server claimed
        first is skipped (the claim in `run` fails) and the next one tried."""
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
            self.kick()

    def _run_guarded(self, job_id: str) -> None:
        # Whatever goes wrong inside a job ends that job, never the worker thread or server.
        claimed = False
        try:
            claimed = self._run(job_id)
        except Exception as exc:
            claimed = True  # runs raise after their claim (claim first, then work)
            log.exception("job %s failed", job_id)
            self.store.finish(job_id, FAILED, error=failure_message(exc))
        finally:
            if claimed:
                with self._lock:
                    self._lost.discard(job_id)
                self._ended(job_id)

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
                self.kick()  # lapsed jobs, or ones a failed look-up left waiting

    def _mark_lost(self, held: set[str]) -> None:
        """A job rendering here whose lease is no longer ours (this server stalled past its
        lease and another resumed the job) stops at the next chunk and writes nothing more."""
        live = set(self._live())
        with self._lock:
            lost = [job_id for job_id in live if job_id not in held and job_id not in self._lost]
            self._lost.update(lost)
        for job_id in lost:
            log.error("job %s: this server lost its lease (stalled longer than a lease?); another server runs "
                      "it now, stopping here", job_id)

    @staticmethod
    def _safe(call: Callable):
        """A store call from a background thread: a database hiccup is logged, never fatal."""
        try:
            return call()
        except Exception:
            log.exception("job store call %s failed; retrying on the next round", getattr(call, "__name__", call))
            return None
