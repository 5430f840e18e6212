"""λ edits of a finished job on the Ray backend, in a Ray worker: the API process never loads a
scene (an uploaded scene is the user's, and its memory is only watched inside a worker).

A finished job's actors are gone (they hold CPUs the next jobs need), so its first λ edit starts
one actor for all its frames that opens the last checkpoint — loads the scene, recomputes the
denoiser's cached features once (a full pass) — re-denoises, then writes the result EXRs on
its own thread after the answer (JobActor.save_results_later). The
actor stays for the next edits (λ-only tail passes) while its job is among the
IDLE_ACTORS_KEPT most recently edited; it asks Ray for no CPU, so it never holds up a job.
"""
from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from typing import Any, Callable

import numpy as np
import ray

from service.jobs.artifacts import JobFiles
from service.jobs.ray_actor import ActorPlan, JobActor
from service.jobs.record import JobRecord, job_spec
from service.jobs.lambda_edits import Relambda
from service.loop.spec import estimated_memory

log = logging.getLogger(__name__)

# A λ actor's result writes take about a second at 2 MP; a stop or a GET waits at most this
# long for them (its runtime may be going down with the server).
FLUSH_SECONDS = 120.0
IDLE_ACTORS_KEPT = 2  # as the thread backend keeps IDLE_LOOPS_KEPT finished loops


class LambdaActors:
    """The warm λ actors of finished jobs, newest last. `call` runs a Ray call and raises the
    backend's WorkerDied when the actor's process is gone (service.jobs.ray_worker._call)."""

    def __init__(self, networks: Callable[[], Any], call: Callable[..., list]) -> None:
        self._networks = networks  # passed by value to each actor (why: RayJobWorker._start_group)
        self._call = call
        self._lock = threading.Lock()
        self._actors: OrderedDict[str, Any] = OrderedDict()

    def relambda(self, job_id: str, record: JobRecord, files: JobFiles, size: tuple[int, int],
                 lam: np.ndarray) -> Relambda:
        """Re-denoise the finished job with `lam` in its λ actor and save its results there."""
        actor = self._actor(job_id, record, files, size)
        started = time.perf_counter()
        try:
            images, full, tail, timings = self._call(actor.set_lambda.remote(lam))[0]
            self._call(actor.save_results_later.remote())  # the result follows λ after the answer
        except Exception:
            self.drop(job_id)  # a dead or broken actor: the next edit starts a fresh one
            raise
        # copied out of the object store: the preview keeps them, and a pinned object outlives a
        # SIGTERM'd raylet badly (see ray_worker.owned_report)
        copies = [np.array(images[f]) for f in sorted(images)]
        hop = time.perf_counter() - started - timings["denoise"]  # the λ map in, the images out, the two calls
        return Relambda(copies, full, tail, timings={**timings, "hop": hop})

    def save_results(self, job_id: str, record: JobRecord, files: JobFiles, size: tuple[int, int]) -> tuple[int, float]:
        """Write the result EXRs of the job's last checkpoint in a worker (a job canceled mid-
        iteration: its actors are gone), then end that worker. Returns the checkpoint's
        (iteration, mean spp)."""
        actor = self._actor(job_id, record, files, size)
        try:
            self._call(actor.save_results.remote())
            return self._call(actor.progress.remote())[0]
        finally:
            self.drop(job_id)

    def _actor(self, job_id: str, record: JobRecord, files: JobFiles, size: tuple[int, int]) -> Any:
        with self._lock:
            actor = self._actors.get(job_id)
            if actor is not None:
                self._actors.move_to_end(job_id)
                return actor
        frames = job_spec(record).frames
        # One thread: giving it the server's torch threads (2) made PUT /jobs/{id}/lambda at 2 MP
        # p50 21.9-31.2 s instead of 1.8-4.1 s on the loaded host (load 15-24, two rounds of
        # bench.lambda_edit_ab --http, commit 5d43ead): its result writes share the process.
        plan = ActorPlan(str(files.root), record, (0, frames), estimated_memory(size[1], size[0], frames), cpus=1)
        actor = ray.remote(JobActor).options(num_cpus=0, max_restarts=0).remote(self._networks(), plan)
        try:
            self._call(actor.open.remote())  # the scene and the checkpoint, loaded in the worker
        except Exception:
            ray.kill(actor, no_restart=True)
            raise
        with self._lock:
            self._actors[job_id] = actor
            retired = []
            while len(self._actors) > IDLE_ACTORS_KEPT:
                retired.append(self._actors.popitem(last=False)[1])
        for old in retired:
            self._flush_quietly(old)
            ray.kill(old, no_restart=True)
        return actor

    def flush(self, job_id: str | None = None) -> None:
        """Wait until the job's (every warm actor's, with None) λ results are written."""
        with self._lock:
            actors = list(self._actors.values()) if job_id is None else [self._actors[job_id]] if job_id in self._actors else []
        for actor in actors:
            self._flush_quietly(actor)

    def drop(self, job_id: str) -> None:
        with self._lock:
            actor = self._actors.pop(job_id, None)
        if actor is not None:
            self._flush_quietly(actor)
            ray.kill(actor, no_restart=True)

    def drop_all(self) -> None:
        with self._lock:
            actors, self._actors = list(self._actors.values()), OrderedDict()
        for actor in actors:
            self._flush_quietly(actor)
            ray.kill(actor, no_restart=True)

    def _flush_quietly(self, actor: Any) -> None:
        """The actor's pending result writes land; a dead actor has nothing left to write."""
        try:
            ray.get(actor.flush_results.remote(), timeout=FLUSH_SECONDS)
        except Exception:  # noqa: BLE001 — its process is gone (or going): nothing to wait for
            log.warning("a λ actor's result writes could not be flushed", exc_info=True)
