"""The Ray backend of the job worker: every running job is a group of Ray actors
(service.jobs.ray_actor) — one for a single frame, one per share of the frames for a sequence —
scheduled with the resources the job needs (CPU, GPU, memory from its estimate).

This process stays the one that talks to the job store: it claims jobs, drives each iteration's
phases, publishes the previews the leader hands back and records the iteration, in the thread
backend's order (checkpoint, previews, record). What the engine adds:

- cancel: the actor's cooperative flag first (it stops within one wavefront chunk), `ray.kill`
  after CANCEL_GRACE_SECONDS whatever it is doing;
- a job over its memory share: its worker's watchdog ends the process and leaves the reason in
  the job folder; the job fails with that message, the server and the other jobs go on;
- a worker process that dies otherwise (`kill -9`, a lost node): the job resumes on new actors
  from its last checkpoint, at most MAX_WORKER_RESTARTS times.

λ edits of a running job go to its actors (they hold the cached features); after the run, to a
λ actor that reopens the checkpoint (service.jobs.ray_lambda): this process never loads a scene.
"""
from __future__ import annotations

import logging
import os
import threading
import time
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np
import ray
from ray.exceptions import RayActorError, RayTaskError

from models.pretrained import Networks
from service.jobs.artifacts import JobFiles
from service.jobs.checkpoint_writer import CheckpointWriter
from service.jobs.lambda_edits import LambdaEdits, LambdaEditsOfRunner, Relambda, require
from service.jobs.previews import PreviewPublisher
from service.jobs.queue_runner import LeaseLost, QueueRunner
from service.jobs.ray_lambda import LambdaActors
from service.jobs.ray_runtime import LocalRay, chain_sigterm, join_cluster
from service.jobs.ray_actor import ACTOR_THREADS, FAILURE_FILE, ActorPlan, IterationReport, JobActor
from service.jobs.record import CANCELED, COMPLETED, FAILED, JobRecord, bundle_scene, job_spec
from service.jobs.store import JobStore
from service.jobs.runner import (DELETE_WAIT_SECONDS, CancelFlags, NoObserver, WorkerObserver, add_timings,
                                 cancel_job, stop_before_delete)
from service.loop.eta import EtaTracker
from service.loop.loop import IterationInterrupted
from service.loop.spec import estimated_memory
from service.loop.stop_message import canceled_message
from service.render.scenes import film_size

log = logging.getLogger(__name__)

CANCEL_GRACE_SECONDS = 1.5  # a cooperative stop takes one wavefront chunk; then the actor is killed
MAX_WORKER_RESTARTS = 3  # a job whose workers keep dying fails instead of looping forever
CPUS_PER_ACTOR = 1
DEATH_SETTLE_SECONDS = 0.5
RUNTIME_POLL_SECONDS = 1.0
RUNTIME_DIED_EXIT_CODE = 75  # EX_TEMPFAIL: systemd's Restart=on-failure, docker's on-failure restart it


def start_local_ray(cpus: int) -> LocalRay:
    """The local runtime `serve --workers N` starts (the tests and `bench --scale` start the same):
    loopback only, token auth, none of the service's secrets in its processes."""
    runtime = LocalRay(cpus)
    runtime.start()
    return runtime


@dataclass(frozen=True)
class RaySettings:
    """`workers`: jobs (or sequence shares) rendered at once; a local Ray runtime gets that many
    CPUs (and a sequence spreads over at most that many). `address`: join that cluster instead
    (`ray start --head` somewhere); then the cluster's resources decide."""

    workers: int = 1
    address: str | None = None
    insecure: bool = False  # join `address` even without Ray's token auth (--insecure-ray)

    def __post_init__(self) -> None:
        if self.workers < 1:
            raise ValueError("workers must be >= 1")


def default_workers() -> int:
    """One worker per core (each actor takes one CPU), at least one."""
    return max(1, os.cpu_count() or 1)


def root_cause(exc: BaseException) -> BaseException:
    """The exception raised inside an actor, through any chain of Ray's wrappers."""
    while isinstance(exc, RayTaskError) and exc.cause is not None and exc.cause is not exc:
        exc = exc.cause
    return exc


def shares(frames: int, workers: int) -> list[tuple[int, int]]:
    """Split frames [0, frames) into at most `workers` contiguous shares, sizes within one."""
    count = max(1, min(frames, workers))
    bounds = [round(i * frames / count) for i in range(count + 1)]
    return [(bounds[i], bounds[i + 1]) for i in range(count)]


class WorkerDied(RuntimeError):
    """A job's worker process ended without finishing its call."""


class RayJobWorker(LambdaEditsOfRunner):
    """The Ray backend: a JobRunner (service/jobs/runner.py) whose jobs run in Ray actors; its
    queue's threads only drive them (one thread per job)."""

    def __init__(self, store: JobStore, networks: Networks, settings: RaySettings = RaySettings(),
                 observer: WorkerObserver = NoObserver()) -> None:
        self.store = store
        self.networks = networks
        self.observer = observer
        self.settings = settings
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._cancel = CancelFlags()
        self.queue = QueueRunner(store, settings.workers, run=self._run, ended=self._cancel.forget,
                                 live=lambda: (), stopping=self._stopping)  # leases: checked before each checkpoint
        self.previews = PreviewPublisher(store)
        self.lambdas = LambdaEdits(store, self.previews, self._relambda, observer.lambda_applied,
                                   flush_elsewhere=lambda job_id: self._lambda_actors.flush(job_id))
        self._groups: dict[str, list] = {}  # job id → its actors, leader first
        self._runtime: LocalRay | None = None  # the local runtime this worker started, if it did
        self._joined = False
        self._gpus = 0
        self._unchain_sigterm: Callable[[], None] = lambda: None
        self._lambda_actors = LambdaActors(lambda: self.networks, _call)

    # -- lifecycle ----------------------------------------------------------------------------

    def start(self) -> None:
        if not ray.is_initialized():
            if self.settings.address:
                join_cluster(self.settings.address, self.settings.insecure)
                self._joined = True
            else:
                self._runtime = start_local_ray(self.settings.workers * CPUS_PER_ACTOR)
        self._unchain_sigterm = chain_sigterm(self._stopping.set)
        if self._runtime is not None:
            threading.Thread(target=self._watch_runtime, name="ray-watch", daemon=True).start()
        self._gpus = 1 if ray.cluster_resources().get("GPU", 0) >= 1 else 0  # asked once: the GCS may be gone later
        self.queue.start()

    def stop(self) -> None:
        """Running jobs stop (cooperatively, then killed) and are requeued to resume next start."""
        started = time.monotonic()
        self._stopping.set()
        self.queue.stop()
        self.lambdas.flush()  # λ edits answered before the stop: their previews and results land
        with self._lock:
            groups = list(self._groups.values())
        for group in groups:
            self._signal_cancel(group)
        self._wait_for_drivers(CANCEL_GRACE_SECONDS * 2)
        with self._lock:  # and the groups started meanwhile: a thread that outlived the first look
            groups = list(self._groups.values())
        for group in groups:
            self._kill(group)
        # The driver threads end before Ray does: one still running would otherwise call Ray after
        # ray.shutdown, and an actor created then starts a fresh, unsealed local runtime (Ray
        # initialises itself on first use).
        self._wait_for_drivers(CANCEL_GRACE_SECONDS * 2)
        self._lambda_actors.drop_all()
        self._unchain_sigterm()
        if self._runtime is not None:
            self._runtime.stop()
        elif self._joined:
            ray.shutdown()
        log.info("Ray backend stopped in %.1f s (running jobs requeued)", time.monotonic() - started)

    def _wait_for_drivers(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while self._claimed() and time.monotonic() < deadline:
            time.sleep(0.05)

    def _is_live(self, job_id: str) -> bool:
        with self._lock:
            return job_id in self._groups

    def worker_pids(self, job_id: str) -> list[int]:
        """The process ids of a running job's actors (leader first); empty when none runs."""
        with self._lock:
            group = list(self._groups.get(job_id, []))
        try:
            return ray.get([actor.pid.remote() for actor in group]) if group else []
        except RayActorError:
            return []  # one just died: the job is between workers

    # -- cancel ---------------------------------------------------------------------------------

    def cancel(self, job_id: str) -> JobRecord:
        """Queued: canceled at once; running: the flag the driver checks, the actors' own flag,
        then `ray.kill` after CANCEL_GRACE_SECONDS."""
        record, running = cancel_job(self.store, self._cancel, job_id)
        with self._lock:
            group = list(self._groups.get(job_id, [])) if running else []
        if group:
            self._signal_cancel(group)
            timer = threading.Timer(CANCEL_GRACE_SECONDS, self._kill, args=(group,))
            timer.daemon = True
            timer.start()
        return record

    @staticmethod
    def _signal_cancel(group: list) -> None:
        for actor in group:
            actor.cancel.remote()

    @staticmethod
    def _kill(group: list) -> None:
        for actor in group:
            ray.kill(actor, no_restart=True)

    # -- running a job --------------------------------------------------------------------------

    def _run(self, job_id: str) -> bool:
        """Claim the job and drive it; False if it was not ours to run (see QueueRunner)."""
        if self._stopping.is_set() or not self.store.claim(job_id):
            return False
        with self._lock:
            self._groups[job_id] = []  # live from the claim on: a delete waits until it ends
        try:
            self._run_attempts(job_id, self._cancel.flag(job_id))
        finally:
            with self._lock:
                self._groups.pop(job_id, None)
        return True

    def _run_attempts(self, job_id: str, cancel: threading.Event) -> None:
        restarts = 0
        while True:
            try:
                self._attempt(job_id, cancel)
                return
            except IterationInterrupted:
                self._interrupted(job_id, cancel)
                return
            except LeaseLost:
                log.error("job %s: this server lost its lease (stalled longer than a lease?); another server runs it "
                          "now, stopping here without writing", job_id)
                return
            except WorkerDied as died:
                failure = self._worker_failure(job_id)
                if failure is not None:
                    self.store.finish(job_id, FAILED, error=failure)
                    return
                if self._stopped_underneath(cancel):
                    self.store.requeue(job_id)  # resumes from its checkpoint on the next start
                    return
                if cancel.is_set() or self._stopping.is_set():
                    self._interrupted(job_id, cancel)
                    return
                restarts += 1
                if restarts > MAX_WORKER_RESTARTS:
                    raise RuntimeError(f"the job's worker died {restarts} times; last: {died}") from died
                log.warning("job %s: its worker died (%s); resuming from the last checkpoint", job_id, died)

    def _stopped_underneath(self, cancel: threading.Event) -> bool:
        """Ray itself died under the job (not just its worker). A signal to the whole process
        group reaches Ray's processes in the same instant as this one: give the signal handler
        and a dying raylet a moment before deciding a worker died on its own."""
        if not cancel.is_set():
            time.sleep(DEATH_SETTLE_SECONDS)
        return self._runtime is not None and self._runtime.failure() is not None

    def _watch_runtime(self) -> None:
        """A local Ray runtime that lost a vital daemon (a raylet killed, or its dashboard agent,
        which takes the raylet down) cannot run jobs again: its running jobs are requeued and
        the server exits non-zero, so its supervisor starts a fresh one that resumes them from
        their checkpoints. Restarting Ray inside this process would leave the driver's Ray
        client half-connected to the dead one."""
        while not self._stopping.wait(RUNTIME_POLL_SECONDS):
            failure = self._runtime.failure() if self._runtime is not None else None
            # A SIGTERM to the process group ends Ray's daemons too: that is a stop, not a failure.
            if failure is None or self._stopping.wait(DEATH_SETTLE_SECONDS):
                continue
            log.error("%s: no job can run; requeuing the running ones and exiting (status %d) so a supervisor "
                      "restarts the server", failure, RUNTIME_DIED_EXIT_CODE)
            for job_id in self._claimed():
                self.store.requeue(job_id)
            self._runtime.remove_token()
            logging.shutdown()
            os._exit(RUNTIME_DIED_EXIT_CODE)

    def _claimed(self) -> list[str]:
        with self._lock:
            return list(self._groups)

    def health_problem(self) -> str | None:
        """Why no job can run here now, or None (GET /healthz answers 503 with it)."""
        if self._stopping.is_set():
            return "the server is stopping"
        if not ray.is_initialized():
            return "not connected to Ray"
        return self._runtime.failure() if self._runtime is not None else None

    def _interrupted(self, job_id: str, cancel: threading.Event) -> None:
        """Stopped inside an iteration: a user cancel keeps what the checkpoint holds; a
        shutdown requeues the job to resume next start."""
        if not cancel.is_set():
            self.store.requeue(job_id)
            return
        record, files, size = require(self.store, job_id), self.files(job_id), self.image_size(job_id)
        iterations, spp = 0, 0.0
        if files.checkpoint.exists() and size is not None:
            # the checkpoint's results are written in a worker: this process never loads a scene
            try:
                iterations, spp = self._lambda_actors.save_results(job_id, record, files, size)
            except Exception:  # noqa: BLE001 — the user asked for a cancel: it ends canceled, without results
                log.exception("job %s: canceled, but its checkpoint's results could not be written", job_id)
        self.store.finish(job_id, CANCELED, stop_reason="canceled", stop_message=canceled_message(iterations, spp))

    def _worker_failure(self, job_id: str) -> str | None:
        """Why a worker ended the job itself (its memory watchdog), if it did."""
        path = self.files(job_id).root / FAILURE_FILE
        return path.read_text() if path.is_file() else None

    def _attempt(self, job_id: str, cancel: threading.Event) -> None:
        record, files = require(self.store, job_id), self.files(job_id)
        (files.root / FAILURE_FILE).unlink(missing_ok=True)
        group = self._start_group(job_id, record, files)
        try:
            effects, resumed_from, done, samples = _call(*[actor.open.remote() for actor in group])[0]
            self.store.set_effects(job_id, effects)
            if resumed_from is not None:
                self.store.set_resumed_from(job_id, resumed_from)
            last = None if done else self._iterate(job_id, record, files, group, cancel, samples)
            self._end(job_id, group, last, cancel)
        finally:
            with self._lock:
                self._groups[job_id] = []
            self._kill(group)

    def _iterate(self, job_id: str, record: JobRecord, files: JobFiles, group: list, cancel: threading.Event,
                 samples: int) -> IterationReport | None:
        timings, last = dict(record.timings), None
        eta = EtaTracker(job_spec(record), record.spp)
        # The previews and the record follow the leader's checkpoint on this thread, while the
        # actors render the next iteration (the leader saves in the background too).
        publisher = CheckpointWriter(f"publish-{job_id[:8]}")
        try:
            while not cancel.is_set() and not self._stopping.is_set():
                report = run_iteration(group, before_finish=lambda: self.queue.hold_lease(job_id))
                started = time.perf_counter()
                publisher.wait()  # one iteration behind at most; a failed checkpoint fails the job here
                io_seconds = {"io": report.timings.get("io", 0.0) + time.perf_counter() - started}
                timings = add_timings(timings, {**report.timings, **io_seconds})
                # the loop's own time (what its time limit counts) is the stages' sum less the I/O
                progress = eta.after(report.iteration + 1, report.spp_mean, {**report.timings, **io_seconds},
                                     sum(timings.values()) - timings.get("io", 0.0), report.stop_reason,
                                     report.predicted_error)
                publisher.submit(lambda report=report, timings=timings, progress=progress: self._record_iteration(
                    job_id, files, group[0], report, timings, progress))
                self.observer.iteration_finished(report.timings, report.samples - samples)
                samples, last = report.samples, report
                if report.stop_reason is not None:
                    break
            publisher.flush()  # the job ends only once its last iteration is on disk and recorded
        finally:
            publisher.close()
        return last

    def _record_iteration(self, job_id: str, files: JobFiles, leader, report: IterationReport,
                          timings: dict[str, float], progress) -> None:
        """On the publisher's thread: once the leader's checkpoint of this iteration is on disk,
        the previews, then the record (the record never claims an iteration a restart could not
        resume from)."""
        _call(leader.checkpointed_through.remote(report.iteration + 1))
        self.previews.publish(job_id, files, report.layers)
        self.store.record_iteration(job_id, report.iteration + 1, report.spp_mean, report.predicted_error,
                                    timings, report.stop_reason, progress)

    def _end(self, job_id: str, group: list, last: IterationReport | None, cancel: threading.Event) -> None:
        finished = last is not None and last.stop_reason not in (None, "canceled")
        if not finished and not cancel.is_set() and self._stopping.is_set():
            self.store.requeue(job_id)
            return
        _call(group[0].save_results.remote())  # the leader holds every frame
        canceled = (cancel.is_set() and not finished) or (last is not None and last.stop_reason == "canceled")
        if canceled:
            record = require(self.store, job_id)
            self.store.finish(job_id, CANCELED, stop_reason="canceled",
                              stop_message=canceled_message(record.iteration, record.spp))
        else:
            self.store.finish(job_id, COMPLETED, stop_reason=last.stop_reason if last else None)

    def _start_group(self, job_id: str, record: JobRecord, files: JobFiles) -> list:
        spec = job_spec(record, files.bundle_dir)
        root = files.bundle_dir if bundle_scene(record) else None
        width, height = film_size(spec.scene, width=spec.width, height=spec.height, params=spec.params, root=root,
                                  frames=spec.frames)
        gpus = self._gpus
        group: list = []
        for share in shares(spec.frames, self.settings.workers):
            memory = estimated_memory(width, height, share[1] - share[0])
            plan = ActorPlan(str(files.root), record, share, memory, CPUS_PER_ACTOR)
            actor_class = ray.remote(JobActor).options(
                num_cpus=CPUS_PER_ACTOR, num_gpus=gpus, memory=int(memory), max_concurrency=ACTOR_THREADS,
                max_restarts=0, name=None)
            with self._lock:  # each actor is started and registered where stop() sees it, never after stop()
                if self._stopping.is_set():
                    self._kill(group)
                    raise IterationInterrupted()  # the job is requeued (_interrupted)
                # The networks go by value (~0.2 MB, pickled per actor), never as a ray.put object
                # the server owns for its life: when Ray's node goes down under the server (a
                # SIGTERM to the whole process group) the driver tries to recover such an object,
                # finds the object store gone and Ray ends the process with status 1 (measured:
                # a kept ray.put ref, raylet SIGTERM'd → driver exit 1; by value → it lives on).
                group.append(actor_class.remote(self.networks, plan))
                self._groups[job_id] = group
        return group

    # -- λ --------------------------------------------------------------------------------------

    def _relambda(self, job_id: str, record: JobRecord, lam: np.ndarray) -> Relambda | None:
        with self._lock:
            group = list(self._groups.get(job_id, []))
        if not group:
            return self._relambda_finished(job_id, record, lam)
        started = time.perf_counter()
        try:
            answers = _call(*[actor.set_lambda.remote(lam) for actor in group])
        except WorkerDied:
            return self._relambda_finished(job_id, require(self.store, job_id), lam)  # it just ended
        images: dict[int, np.ndarray] = {}
        for owned, *_ in answers:
            images.update({f: np.array(image) for f, image in owned.items()})  # out of the object store (ray_lambda)
        full, tail = sum(a[1] for a in answers), sum(a[2] for a in answers)
        slowest = max((a[3] for a in answers), key=lambda t: t["denoise"])  # the actors run side by side
        hop = time.perf_counter() - started - slowest["denoise"]
        return Relambda([images[f] for f in sorted(images)], full, tail, timings={**slowest, "hop": hop})


    def _relambda_finished(self, job_id: str, record: JobRecord, lam: np.ndarray) -> Relambda | None:
        """A job without running actors: finished, in its λ actor (service.jobs.ray_lambda);
        queued or starting, nothing to do (its loop reads the saved map when it opens)."""
        files, size = self.files(job_id), self.image_size(job_id)
        if record.state != COMPLETED or not files.checkpoint.exists() or size is None:
            return None
        return self._lambda_actors.relambda(job_id, record, files, size, lam)

    # -- the rest of the JobRunner interface ----------------------------------------------------

    def submit(self, job_id: str) -> None:
        self.queue.kick()

    def files(self, job_id: str) -> JobFiles:
        return JobFiles(self.store.job_dir(job_id))

    def delete(self, job_id: str, wait_seconds: float = DELETE_WAIT_SECONDS) -> None:
        """Forget a job, its files and its λ actor; a queued or running job is canceled first."""
        stop_before_delete(self, self.store, job_id, self._is_live, wait_seconds)
        self._lambda_actors.drop(job_id)
        self.previews.forget(job_id)
        self.store.delete(job_id)


def _call(*refs) -> list:
    """ray.get that raises what the actor raised, or WorkerDied when its process is gone."""
    try:
        return ray.get(list(refs))
    except RayActorError as exc:
        raise WorkerDied(str(exc).splitlines()[0] if str(exc) else exc.__class__.__name__) from exc
    except RayTaskError as exc:
        cause = root_cause(exc)
        if isinstance(cause, RayActorError):
            raise WorkerDied(str(cause).splitlines()[0]) from exc
        raise cause from None


def run_iteration(group: list, before_finish: Callable[[], None] = lambda: None) -> IterationReport:
    """One iteration over a job's actors: render, exchange the buffers, denoise, exchange the
    outputs, finish. Frames pass between the actors as object references, never through here;
    each phase starts once the last one ended everywhere (and raised nothing). `before_finish`
    runs before the finish phase, in which the leader writes the checkpoint (it may raise to
    stop the job there)."""
    started = time.perf_counter()
    exchange = len(group) > 1
    rendered = [ref for ref in _call(*[actor.render_phase.remote(exchange) for actor in group]) if ref is not None]
    denoised = [ref for ref in _call(*[actor.denoise_phase.remote(rendered) for actor in group]) if ref is not None]
    before_finish()
    seconds = time.perf_counter() - started  # one clock for all actors: the same time-limit decision
    return owned_report(_call(*[actor.finish_phase.remote(denoised, seconds) for actor in group])[0])


def owned_report(report: IterationReport) -> IterationReport:
    """The report with its image layers copied out of Ray's object store. `ray.get` hands numpy
    arrays that map the store's shared memory and keep the object pinned until they are freed;
    the previews are published from them on a background thread while the next iteration renders,
    so they would be freed — and the pin released over the raylet's socket — after a SIGTERM to
    the process group has ended the raylet, and Ray's driver ends the process (status 1) when it
    finds its raylet gone. Copied here, the store's object is released at once, on this thread."""
    layers = [{name: None if image is None else np.array(image) for name, image in frame.items()}
              for frame in report.layers]
    return replace(report, layers=layers)
