"""Runs render loops off the event loop and keeps each job's record, checkpoint and previews
current.

One thread pool (`concurrency` threads, default 1) runs jobs: each thread takes the store's next
queued job (highest priority, then oldest), and a lease thread keeps this server's leases and
resumes jobs whose server died (service/jobs/queue_runner.py). After every
iteration the worker has the job's checkpoint (service/jobs/checkpoints.py) copy the loop state
and save the copy on its background thread, which then writes the preview layers, bumps the
preview version and updates the record, in that order, so the record never claims an iteration
a restart could not resume from, while the loop renders the next iteration. Every ending of a
job waits for that write first. λ changes go through a per-job latest-wins
mailbox and re-denoise from the loop's cached features (`RenderLoop.set_lambda`).
"""
from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, replace
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable, Protocol

import numpy as np

from models.pretrained import Networks
from service.exr import ExrFrame
from service.jobs.artifacts import JobFiles, Preview
from service.jobs.checkpoints import JobCheckpoint
from service.jobs.errors import JobConflict, JobNotFound
from service.jobs.latest import LatestWins
from service.jobs.queue_runner import LeaseLost, QueueRunner
from service.jobs.record import CANCELED, COMPLETED, FAILED, JobRecord, bundle_scene, job_spec
from service.jobs.store import JobStore
from service.loop.eta import EtaTracker
from service.loop.loop import IterationInterrupted, RenderLoop
from service.loop.spec import IterationRecord, LoopSpec
from service.loop.state import LoopState
from service.loop.stop_message import canceled_message


log = logging.getLogger(__name__)

IDLE_LOOPS_KEPT = 2  # finished loops kept in memory so λ changes after the run stay cheap
LAMBDA_WAIT_SECONDS = 300.0
DELETE_WAIT_SECONDS = 30.0  # a running job stops within one chunk; this bounds a stuck one


@dataclass(frozen=True)
class LambdaApplied:
    """What one λ application did: the preview version showing it, and the denoiser work it
    took (full forward passes vs. λ-only tail passes from cached features)."""

    version: int
    full_passes: int = 0
    tail_passes: int = 0


@dataclass(frozen=True)
class Relambda:
    """A λ re-denoise: the new image per frame, the denoiser work it took, and how to build the
    result frames from it (None where the loop lives elsewhere and keeps them itself)."""

    images: list[np.ndarray]
    full_passes: int = 0
    tail_passes: int = 0
    results: Callable[[], list[ExrFrame]] | None = None


def _failure_message(exc: BaseException) -> str:
    text = str(exc).strip() or exc.__class__.__name__
    return f"{exc.__class__.__name__}: {text}" if not isinstance(exc, ValueError) else text


def add_timings(total: dict[str, float], more: dict[str, float]) -> dict[str, float]:
    merged = dict(total)
    for stage, seconds in more.items():
        merged[stage] = merged.get(stage, 0.0) + float(seconds)
    return merged


class WorkerObserver(Protocol):
    """Told what the worker did, for monitoring (service.api.metrics)."""

    def iteration_finished(self, timings: dict[str, float], samples: int) -> None:
        """One iteration: seconds per stage, samples it rendered over all frames."""

    def lambda_applied(self, seconds: float) -> None:
        """A λ edit, from its request to the preview version that shows it."""


class NoObserver:
    def iteration_finished(self, timings: dict[str, float], samples: int) -> None:
        pass

    def lambda_applied(self, seconds: float) -> None:
        pass


def total_samples(buffers: list) -> int:
    """Samples accumulated in a job's frame buffers, all frames together."""
    return sum(int(buf.spp.sum()) for buf in buffers)


def preview_layers(loop: RenderLoop, record: IterationRecord) -> list[dict[str, np.ndarray | None]]:
    """Each frame's preview layers after an iteration (JobFiles.save_preview takes them)."""
    return state_preview_layers(loop.state, record)


def state_preview_layers(state: LoopState, record: IterationRecord) -> list[dict[str, np.ndarray | None]]:
    """The preview layers of `record` with the λ map of `state` (a snapshot's, when written in
    the background)."""
    lam = state.lam_map
    return [
        {
            "denoised": record.denoised[f] if record.denoised else buf.raw,
            "noisy": buf.raw,
            "error": record.error[f] if f < len(record.error) else None,
            "spp": buf.spp.astype(np.float32),
            "lambda": lam,
        }
        for f, buf in enumerate(record.buffers)
    ]


class JobWorker(QueueRunner):
    def __init__(self, store: JobStore, networks: Networks, concurrency: int = 1,
                 observer: WorkerObserver = NoObserver()) -> None:
        if concurrency < 1:
            raise ValueError("concurrency must be >= 1")
        self.store = store
        self.observer = observer
        self.networks = networks  # loaded once at start-up, shared by every job's loop
        self._pool = ThreadPoolExecutor(max_workers=concurrency, thread_name_prefix="render")
        self._lock = threading.Lock()
        self._cancel: dict[str, threading.Event] = {}
        self._live: dict[str, RenderLoop] = {}  # jobs rendering right now
        self._idle: OrderedDict[str, RenderLoop] = OrderedDict()  # finished, kept for λ
        self._publish_locks: dict[str, threading.Lock] = {}
        self._lambda: dict[str, LatestWins[tuple[np.ndarray, float | None], LambdaApplied]] = {}
        self._stopping = threading.Event()
        self._concurrency = concurrency
        self._draining = 0  # pool tasks taking queued jobs (at most `concurrency`)
        self._lost: set[str] = set()  # live jobs whose lease another server took over
        self._checkpoints: dict[str, JobCheckpoint] = {}  # live jobs' checkpoints (their background writes)
        self._eta: dict[str, EtaTracker] = {}  # live jobs' measured iteration costs (service/loop/eta.py)
        self._leases = threading.Thread(target=self._keep_leases, name="leases", daemon=True)

    # -- lifecycle ----------------------------------------------------------------------------

    def start(self) -> None:
        """Jobs whose server died (this one's last life, or another whose lease lapsed) resume;
        queued ones run. A live other server's running jobs stay its own."""
        for job_id in self.store.requeue_abandoned():
            log.info("job %s was running on a server that is gone: resuming from its checkpoint", job_id)
        self._leases.start()
        self._kick()

    def delete(self, job_id: str, wait_seconds: float = DELETE_WAIT_SECONDS) -> None:
        """Forget a job and its files; a queued or running job is canceled first."""
        record = self._require(job_id)
        if not record.finished:
            self.cancel(job_id)  # queued: at once; running: within one wavefront chunk
            deadline = time.monotonic() + wait_seconds
            while self._is_live(job_id) and time.monotonic() < deadline:
                time.sleep(0.05)
            if self._is_live(job_id):
                raise JobConflict(f"job {job_id} is still stopping; retry the delete in a moment")
        with self._lock:
            self._idle.pop(job_id, None)
            self._publish_locks.pop(job_id, None)
        self.store.delete(job_id)

    def _is_live(self, job_id: str) -> bool:
        with self._lock:
            return job_id in self._live

    def health_problem(self) -> str | None:
        """Why no job can run here now, or None (GET /healthz answers 503 with it)."""
        return "the server is stopping" if self._stopping.is_set() else None

    def stop(self) -> None:
        """Ask running loops to stop within one wavefront chunk; they stay resumable."""
        self._stopping.set()
        self._pool.shutdown(wait=False, cancel_futures=True)

    def submit(self, job_id: str) -> None:
        """A job was queued: a free thread takes the queue's next job (the queue's order, by
        priority, decides which; it may be this one or a more urgent one)."""
        self._kick()

    def files(self, job_id: str) -> JobFiles:
        return JobFiles(self.store.job_dir(job_id))

    # -- cancel ---------------------------------------------------------------------------------

    def _cancel_event(self, job_id: str) -> threading.Event:
        with self._lock:
            return self._cancel.setdefault(job_id, threading.Event())

    def cancel(self, job_id: str) -> JobRecord:
        record = self._require(job_id)
        if record.finished:
            raise JobConflict(f"job {job_id} is already {record.state}")
        if not self.store.cancel_if_queued(job_id):
            # Running: the loop checks the flag after every wavefront chunk and stops.
            self._cancel_event(job_id).set()
        return self._require(job_id)

    def _require(self, job_id: str) -> JobRecord:
        record = self.store.get(job_id)
        if record is None:
            raise JobNotFound(f"no job with id {job_id!r}")
        return record

    # -- running a job ------------------------------------------------------------------------

    def _run_guarded(self, job_id: str) -> None:
        # Whatever goes wrong inside a job ends that job, never the worker thread or server.
        try:
            self._run(job_id)
        except Exception as exc:
            log.exception("job %s failed", job_id)
            self.store.finish(job_id, FAILED, error=_failure_message(exc))
        finally:
            with self._lock:
                self._live.pop(job_id, None)
                self._cancel.pop(job_id, None)
                self._lost.discard(job_id)
                self._eta.pop(job_id, None)

    def _run(self, job_id: str) -> None:
        if self._stopping.is_set() or not self.store.claim(job_id):
            return  # canceled while queued, or the server is going down
        record = self._require(job_id)
        files = self.files(job_id)
        checkpoint = files.checkpoint  # this job's one instance: its background writes go through it
        loop = self._open_loop(job_id, record, files, checkpoint)
        with self._lock:
            self._eta[job_id] = EtaTracker(loop.spec, loop.state.spp_mean)
            self._checkpoints[job_id] = checkpoint
        try:
            self._render(job_id, record, loop, files, checkpoint)
        finally:
            checkpoint.close()  # a write still running (the render failed) lands before the job is marked
            with self._lock:
                self._checkpoints.pop(job_id, None)

    def _render(self, job_id: str, record: JobRecord, loop: RenderLoop, files: JobFiles,
                checkpoint: JobCheckpoint) -> None:
        """Run the loop; every ending first flushes the background writer, so the record, the
        checkpoint and the previews are complete (and a failed write fails the job) before the
        job is completed, canceled, requeued or left to the server that took it over."""
        cancel = self._cancel_event(job_id)
        should_stop = lambda: cancel.is_set() or self._stopping.is_set() or self._lease_lost(job_id)  # noqa: E731
        timings = dict(record.timings)
        last: IterationRecord | None = None
        samples = total_samples(loop.state.buffers)  # a resumed job's earlier samples are not counted again
        try:
            for last in loop.run(should_stop=should_stop):
                timings = self._finish_iteration(job_id, loop, files, last, timings)
                self.observer.iteration_finished(last.timings, total_samples(last.buffers) - samples)
                samples = total_samples(last.buffers)
        except LeaseLost:
            checkpoint.wait()
            log.error("job %s: this server lost its lease (stalled longer than a lease?); another server runs it "
                      "now, stopping here without writing", job_id)
            return
        except IterationInterrupted:
            checkpoint.wait()
            # Stopped inside an iteration (within one wavefront chunk): the in-memory buffers
            # are partial, the checkpoint of the last finished iteration is what counts.
            if self._lease_lost(job_id):
                return  # stopped because another server took it over: nothing here to write
            if not cancel.is_set():
                self.store.requeue(job_id)  # server shutdown: resume from the checkpoint next start
                return
            self._complete(job_id, self._checkpointed_loop(record, files), files, None, canceled=True)
            return
        checkpoint.wait()
        finished = last is not None and last.stop_reason not in (None, "canceled")
        if not finished and not cancel.is_set() and self._stopping.is_set():
            self.store.requeue(job_id)  # server shutdown, not a user cancel: resume next start
            return
        if self._lease_lost(job_id):
            return  # another server resumed it from the checkpoint: the job and its files are theirs
        # A cancel that arrives during the last iteration comes too late: the job is complete.
        self._complete(job_id, loop, files, last, canceled=cancel.is_set() and not finished)

    def _make_loop(self, record: JobRecord, files: JobFiles, state: LoopState | None) -> RenderLoop:
        # An uploaded scene may read files from its whole bundle, nothing outside it.
        root = files.bundle_dir if bundle_scene(record) else None
        return RenderLoop(job_spec(record, files.bundle_dir), self.networks, state=state, scene_root=root)

    def _checkpointed_loop(self, record: JobRecord, files: JobFiles) -> RenderLoop | None:
        state = files.checkpoint.load()
        return None if state is None else self._make_loop(record, files, state)

    def _open_loop(self, job_id: str, record: JobRecord, files: JobFiles, checkpoint: JobCheckpoint) -> RenderLoop:
        state = checkpoint.load()
        loop = self._make_loop(record, files, state)
        self.store.set_effects(job_id, loop.effects.as_record())
        if state is not None:
            self.store.set_resumed_from(job_id, state.iteration)
        with self._lock:
            self._live[job_id] = loop
        # Registered first, then read: a λ request that missed the live loop saved its map
        # before we read it here (see _apply_lambda), so no λ change is lost on the way in.
        lam = files.load_lambda()
        if lam is not None and lam.shape == loop.state.lam_map.shape:
            loop.state.lam_map = lam  # newer than the checkpoint's copy
        return loop

    def _finish_iteration(
        self, job_id: str, loop: RenderLoop, files: JobFiles, record: IterationRecord, timings: dict[str, float]
    ) -> dict[str, float]:
        """Hand the iteration's checkpoint, previews and record to the background writer; the
        loop renders the next iteration meanwhile. "io" counts what the render path still pays:
        waiting for the previous write and copying the state."""
        if not self.store.renew_lease(job_id):  # the checkpoint is only ours to write while we hold the job
            with self._lock:
                self._lost.add(job_id)
            raise LeaseLost(job_id)
        with self._lock:
            checkpoint = self._checkpoints[job_id]
        started = time.perf_counter()
        snapshot = checkpoint.snapshot(loop.state)  # after the last write landed; a failed one fails the job here
        written = replace(record, buffers=snapshot.buffers, error=list(snapshot.error_maps),
                          denoised=list(record.denoised))
        io_seconds = {"io": time.perf_counter() - started}
        timings = add_timings(add_timings(timings, record.timings), io_seconds)
        with self._lock:
            eta = self._eta.get(job_id)
        progress = None if eta is None else eta.after(
            snapshot.iteration, record.spp_mean, {**record.timings, **io_seconds}, snapshot.elapsed,
            record.stop_reason, record.predicted_error)
        checkpoint.write_in_background(
            snapshot, then=lambda saved: self._publish_iteration(job_id, files, saved, written, timings, progress))
        return timings

    def _publish_iteration(self, job_id: str, files: JobFiles, snapshot: LoopState, record: IterationRecord,
                           timings: dict[str, float], progress) -> None:
        """On the checkpoint's writer thread once the checkpoint landed, in the order restarts
        rely on: checkpoint, previews, record (the record never claims an iteration a restart
        could not resume from)."""
        self._publish(job_id, files, state_preview_layers(snapshot, record))
        self.store.record_iteration(
            job_id, record.iteration + 1, record.spp_mean, record.predicted_error, timings, record.stop_reason, progress
        )

    def _publish(self, job_id: str, files: JobFiles, frames: list[dict[str, np.ndarray | None]]) -> int:
        """Write all frames' previews under one new version; returns it."""
        with self._publish_lock(job_id):
            version = self.store.bump_preview_version(job_id)
            for f, layers in enumerate(frames):
                files.save_preview(f, Preview(version=version, layers=layers))
            return version

    def _publish_lock(self, job_id: str) -> threading.Lock:
        with self._lock:
            return self._publish_locks.setdefault(job_id, threading.Lock())

    def _complete(
        self, job_id: str, loop: RenderLoop | None, files: JobFiles, last: IterationRecord | None, canceled: bool
    ) -> None:
        stop_reason = last.stop_reason if last is not None else ("canceled" if canceled else None)
        if loop is not None and loop.state.iteration > 0:
            files.save_results(loop.result_frames())
        if canceled or stop_reason == "canceled" or loop is None:
            message = canceled_message(loop.state.iteration, loop.state.spp_mean) if loop else canceled_message()
            self.store.finish(job_id, CANCELED, stop_reason="canceled", stop_message=message)
            return
        self._keep_idle(job_id, loop)
        self.store.finish(job_id, COMPLETED, stop_reason=stop_reason)

    def _keep_idle(self, job_id: str, loop: RenderLoop) -> None:
        with self._lock:
            self._idle[job_id] = loop
            self._idle.move_to_end(job_id)
            while len(self._idle) > IDLE_LOOPS_KEPT:
                self._idle.popitem(last=False)

    # -- λ --------------------------------------------------------------------------------------

    def image_size(self, job_id: str) -> tuple[int, int] | None:
        """(H, W) of the job's images, once known (spec, or the first preview)."""
        spec = job_spec(self._require(job_id))
        if spec.width and spec.height:
            return spec.height, spec.width
        preview = self.files(job_id).load_preview(0)
        if preview is not None and preview.layers.get("noisy") is not None:
            return preview.layers["noisy"].shape[:2]
        return None

    def current_lambda(self, job_id: str, shape: tuple[int, int]) -> np.ndarray:
        record = self._require(job_id)
        lam = self.files(job_id).load_lambda()
        if lam is not None and lam.shape == shape:
            return lam
        return np.full(shape, job_spec(record).lam, dtype=np.float32)

    def set_lambda(self, job_id: str, lam: np.ndarray, value: float | None = None,
                   sequence: int | None = None) -> LambdaApplied:
        """Keep `lam` with the job and re-denoise from cached features. Under a burst only the
        newest request is applied (newest by the client's `sequence` when it sends one, else
        by arrival); every caller gets the version that shows it."""
        started = time.perf_counter()
        record = self._require(job_id)
        if record.state in (FAILED, CANCELED):
            raise JobConflict(f"job {job_id} is {record.state}: there is nothing left to re-denoise")
        mailbox = self._lambda_mailbox(job_id)
        applied = mailbox.wait(mailbox.submit((lam, value), order=sequence), timeout=LAMBDA_WAIT_SECONDS)
        self.observer.lambda_applied(time.perf_counter() - started)
        return applied

    def _lambda_mailbox(self, job_id: str) -> LatestWins[tuple[np.ndarray, float | None], LambdaApplied]:
        with self._lock:
            if job_id not in self._lambda:
                self._lambda[job_id] = LatestWins(
                    lambda request: self._apply_lambda(job_id, *request), name=f"lambda-{job_id[:8]}"
                )
            return self._lambda[job_id]

    def _apply_lambda(self, job_id: str, lam: np.ndarray, value: float | None) -> LambdaApplied:
        # Persisted here, on the one thread that applies this job's λ, so the saved map is
        # always the newest request's; later iterations and restarts read it.
        files = self.files(job_id)
        files.save_lambda(lam)
        self.store.set_lambda_value(job_id, value)
        record = self._require(job_id)
        done = self._relambda(job_id, record, lam)
        if done is None:
            return LambdaApplied(record.preview_version)  # nothing rendered yet: used from iteration 1
        if not done.images:
            return LambdaApplied(record.preview_version, done.full_passes, done.tail_passes)
        frames = []
        for f, image in enumerate(done.images):
            previous = files.load_preview(f)
            layers = dict(previous.layers) if previous else {"noisy": None, "error": None, "spp": None}
            frames.append({**layers, "denoised": image, "lambda": lam})
        version = self._publish(job_id, files, frames)
        if done.results is not None and self._require(job_id).state == COMPLETED:
            files.save_results(done.results())  # the result follows λ after the run too
        return LambdaApplied(version, done.full_passes, done.tail_passes)

    def _relambda(self, job_id: str, record: JobRecord, lam: np.ndarray) -> Relambda | None:
        """Re-denoise the job's frames with `lam` wherever its loop lives (here: this process);
        None when nothing was rendered yet."""
        loop = self._loop_for_lambda(job_id, record)
        if loop is None:
            return None
        session = loop.session
        full_before, tail_before = (session.full_calls, session.tail_calls) if session else (0, 0)
        images = loop.set_lambda(lam)
        full, tail = (session.full_calls - full_before, session.tail_calls - tail_before) if session else (0, 0)
        return Relambda(images, full, tail, results=loop.result_frames)

    def _loop_for_lambda(self, job_id: str, record: JobRecord) -> RenderLoop | None:
        with self._lock:
            loop = self._live.get(job_id) or self._idle.get(job_id)
        if loop is not None or record.state != COMPLETED:
            return loop  # queued or starting: the loop reads the saved map when it opens
        files = self.files(job_id)
        state = files.checkpoint.load()
        if state is None:
            return None
        # After a restart: rebuild from the checkpoint; set_lambda recomputes the cache once.
        loop = self._make_loop(record, files, state)
        self._keep_idle(job_id, loop)
        return loop
