"""Runs render loops off the event loop and keeps each job's record, checkpoint and previews
current.

One thread pool (`concurrency` threads, default 1) runs jobs: each thread takes the store's next
queued job (highest priority, then oldest), and a lease thread keeps this server's leases and
resumes jobs whose server died (service/jobs/queue_runner.py). After every
iteration the worker has the job's checkpoint (service/jobs/checkpoints.py) copy the loop state
and save the copy on its background thread, which then writes the preview layers, bumps the
preview version and updates the record, in that order, so the record never claims an iteration
a restart could not resume from, while the loop renders the next iteration. Every ending of a
job waits for that write first. λ changes go through service/jobs/lambda_edits.py (a per-job
latest-wins mailbox) and re-denoise from the loop's cached features (`RenderLoop.set_lambda`).
"""
from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from dataclasses import replace

import numpy as np

from models.pretrained import Networks
from service.jobs.artifacts import JobFiles
from service.jobs.checkpoints import JobCheckpoint
from service.jobs.lambda_edits import LambdaEdits, LambdaEditsOfRunner, Relambda, require
from service.jobs.previews import PreviewPublisher, state_preview_layers
from service.jobs.queue_runner import LeaseLost, QueueRunner
from service.jobs.record import CANCELED, COMPLETED, JobRecord, bundle_scene, job_spec
from service.jobs.runner import (DELETE_WAIT_SECONDS, CancelFlags, NoObserver, WorkerObserver, add_timings,
                                 cancel_job, stop_before_delete, total_samples)
from service.jobs.store import JobStore
from service.loop.eta import EtaTracker
from service.loop.loop import IterationInterrupted, RenderLoop
from service.loop.spec import IterationRecord
from service.loop.state import LoopState
from service.loop.stop_message import canceled_message


log = logging.getLogger(__name__)

IDLE_LOOPS_KEPT = 2  # finished loops kept in memory so λ changes after the run stay cheap


class JobWorker(LambdaEditsOfRunner):
    """The thread backend: a JobRunner (service/jobs/runner.py) whose jobs' loops run in
    `concurrency` threads of this process."""

    def __init__(self, store: JobStore, networks: Networks, concurrency: int = 1,
                 observer: WorkerObserver = NoObserver()) -> None:
        self.store = store
        self.observer = observer
        self.networks = networks  # loaded once at start-up, shared by every job's loop
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._cancel = CancelFlags()
        self._live: dict[str, RenderLoop] = {}  # jobs rendering right now
        self._idle: OrderedDict[str, RenderLoop] = OrderedDict()  # finished, kept for λ
        self._checkpoints: dict[str, JobCheckpoint] = {}  # live jobs' checkpoints (their background writes)
        self._eta: dict[str, EtaTracker] = {}  # live jobs' measured iteration costs (service/loop/eta.py)
        self.queue = QueueRunner(store, concurrency, run=self._run, ended=self._ended, live=self._live_ids,
                                 stopping=self._stopping)
        self.previews = PreviewPublisher(store)
        self.lambdas = LambdaEdits(store, self.previews, self._relambda, observer.lambda_applied)

    # -- lifecycle ----------------------------------------------------------------------------

    def start(self) -> None:
        self.queue.start()

    def stop(self) -> None:
        """Ask running loops to stop within one wavefront chunk; they stay resumable."""
        self._stopping.set()
        self.queue.stop()
        self.lambdas.flush()  # λ edits answered before the stop: their previews and results land

    def submit(self, job_id: str) -> None:
        """A job was queued: a free thread takes the queue's next job (the queue's order, by
        priority, decides which; it may be this one or a more urgent one)."""
        self.queue.kick()

    def health_problem(self) -> str | None:
        """Why no job can run here now, or None (GET /healthz answers 503 with it)."""
        return "the server is stopping" if self._stopping.is_set() else None

    def files(self, job_id: str) -> JobFiles:
        return JobFiles(self.store.job_dir(job_id))

    def cancel(self, job_id: str) -> JobRecord:
        """Queued: canceled at once; running: the loop checks the flag after every wavefront
        chunk and stops."""
        return cancel_job(self.store, self._cancel, job_id)[0]

    def delete(self, job_id: str, wait_seconds: float = DELETE_WAIT_SECONDS) -> None:
        """Forget a job and its files; a queued or running job is canceled first."""
        stop_before_delete(self, self.store, job_id, self._is_live, wait_seconds)
        with self._lock:
            self._idle.pop(job_id, None)
        self.previews.forget(job_id)
        self.store.delete(job_id)

    def _is_live(self, job_id: str) -> bool:
        with self._lock:
            return job_id in self._live

    def _live_ids(self) -> list[str]:
        with self._lock:
            return list(self._live)

    def _ended(self, job_id: str) -> None:
        with self._lock:
            self._live.pop(job_id, None)
            self._eta.pop(job_id, None)
        self._cancel.forget(job_id)

    # -- running a job ------------------------------------------------------------------------

    def _run(self, job_id: str) -> bool:
        """Claim the job and run it; False if it was not ours to run (see QueueRunner)."""
        if self._stopping.is_set() or not self.store.claim(job_id):
            return False  # canceled while queued, claimed by another thread, or the server is going down
        record = require(self.store, job_id)
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
        return True

    def _render(self, job_id: str, record: JobRecord, loop: RenderLoop, files: JobFiles,
                checkpoint: JobCheckpoint) -> None:
        """Run the loop; every ending first flushes the background writer, so the record, the
        checkpoint and the previews are complete (and a failed write fails the job) before the
        job is completed, canceled, requeued or left to the server that took it over."""
        cancel = self._cancel.flag(job_id)
        should_stop = lambda: cancel.is_set() or self._stopping.is_set() or self.queue.lease_lost(job_id)  # noqa: E731
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
            if self.queue.lease_lost(job_id):
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
        if self.queue.lease_lost(job_id):
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
        self.queue.hold_lease(job_id)  # the checkpoint is only ours to write while we hold the job
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
        self.previews.publish(job_id, files, state_preview_layers(snapshot, record))
        self.store.record_iteration(
            job_id, record.iteration + 1, record.spp_mean, record.predicted_error, timings, record.stop_reason, progress
        )

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

    # -- λ: re-denoise wherever the job's loop lives (service/jobs/lambda_edits.py does the rest) --

    def _relambda(self, job_id: str, record: JobRecord, lam: np.ndarray) -> Relambda | None:
        """Re-denoise the job's frames with `lam` wherever its loop lives (here: this process);
        None when nothing was rendered yet."""
        loop = self._loop_for_lambda(job_id, record)
        if loop is None:
            return None
        done = loop.counted_set_lambda(lam)
        return Relambda(done.images, done.full_passes, done.tail_passes, results=loop.result_frames, timings=done.timings)

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
