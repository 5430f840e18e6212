"""One running job inside a Ray worker process: the Ray backend's actor (service.jobs.ray_worker
drives it).

The actor holds what makes a job cheap to keep going — the loaded scene, the networks and the
denoiser's cached pre-λ features — so the job's λ edits are routed to it. A sequence fanned out
over several workers has one actor per share of its frames; each iteration runs in three phases
so the frames can be exchanged through Ray's object store between them:

    render_phase    allocate + render the owned frames          → their buffers
    denoise_phase   adopt the other shares' buffers (the temporal window reads them),
                    denoise + predict error of the owned frames   → their outputs
    finish_phase    adopt the other shares' outputs, count the iteration, apply the stop rules;
                    the leader (the share holding frame 0) checkpoints and returns the previews

Every actor ends the phase with the whole job's state, so all of them reach the same stop
decision, and any of them could checkpoint; the leader does. Artifacts are written under the
data dir that all workers share.
"""
from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass, field

import drjit as dr
import numpy as np
import ray
import torch

from models.pretrained import Networks
from service.atomic import atomic_write_bytes
from service.jobs.artifacts import JobFiles
from service.jobs.latest_writer import LatestWriter
from service.jobs.record import JobRecord, bundle_scene, job_spec
from service.jobs.previews import preview_layers
from service.jobs.runner import total_samples
from service.loop.loop import RenderLoop
from service.memory_reuse import keep_freed_memory
from service.render.runtime import VARIANT_ENV, mitsuba

GPU_VARIANT = "cuda_ad_rgb"
MEMORY_POLL_SECONDS = 0.05
MEMORY_EXIT_CODE = 86  # the watchdog's exit status: the driver reads the failure file beside it
FAILURE_FILE = "worker_failure.txt"  # in the job folder: why a worker ended the job
# Runs phases, a cancel flag and λ edits side by side (a cancel must reach a rendering actor).
ACTOR_THREADS = 8

FrameOutputs = dict[int, tuple[np.ndarray, np.ndarray | None, np.ndarray]]


@dataclass(frozen=True)
class ActorPlan:
    """What the driver hands one actor: its job, its frames, its resources."""

    job_dir: str
    record: JobRecord
    owned: tuple[int, int]  # frames [start, stop) this actor renders and denoises
    memory_share: float  # bytes the job's share may add to the worker process (its estimate)
    cpus: int = 1

    @property
    def leader(self) -> bool:
        return self.owned[0] == 0


@dataclass
class IterationReport:
    """One finished iteration as the driver records it; `layers` only from the leader."""

    iteration: int
    spp_mean: float
    predicted_error: float | None
    stop_reason: str | None
    samples: int  # samples in all frames' buffers after this iteration
    timings: dict[str, float] = field(default_factory=dict)
    layers: list[dict[str, np.ndarray | None]] = field(default_factory=list)


def resident_bytes() -> int:
    """This process's resident memory (Linux /proc; what the kernel's OOM killer counts)."""
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


class MemoryWatch:
    """Ends the worker process when the job grows past its share: memory is the one resource
    that cannot wait for a cooperative stop, and ending this process frees it at once while
    the server and the other workers live on. The reason goes to the job folder first."""

    def __init__(self, share: float, failure_path: str) -> None:
        self.share = share
        self.failure_path = failure_path
        self.baseline = resident_bytes()  # Python, Ray, torch, Mitsuba, the networks: not the job's
        threading.Thread(target=self._watch, name="memory-watch", daemon=True).start()

    def _watch(self) -> None:
        while True:
            used = resident_bytes() - self.baseline
            if used > self.share:
                message = (f"the job used {used / 2**30:.2f} GiB, over its memory share of {self.share / 2**30:.2f} GiB "
                           "(the estimate for its image size and frames); its worker was stopped")
                atomic_write_bytes(self.failure_path, message.encode())
                os._exit(MEMORY_EXIT_CODE)
            time.sleep(MEMORY_POLL_SECONDS)


def use_devices(networks: Networks, cpus: int) -> Networks:
    """CPU threads as scheduled; with a GPU assigned, Mitsuba's CUDA variant and torch on CUDA.
    Freed memory stays in the actor's process (service.memory_reuse), as in the CLI's."""
    keep_freed_memory()
    torch.set_num_threads(max(1, cpus))
    gpu = bool(ray.get_gpu_ids())
    if gpu:
        os.environ[VARIANT_ENV] = GPU_VARIANT  # read by mitsuba() when it first picks the variant
        networks.denoiser.to("cuda")
        networks.error_predictor.to("cuda")
    mitsuba()
    if not gpu:
        dr.set_thread_count(max(1, cpus))  # the LLVM backend's pool: the cores this actor was given
    return networks


class JobActor:
    """Made a Ray actor by service.jobs.ray_worker (`ray.remote(JobActor).options(...)`)."""

    def __init__(self, networks: Networks, plan: ActorPlan) -> None:
        self.plan = plan
        self.files = JobFiles(plan.job_dir)
        self.checkpoint = self.files.checkpoint  # written by the leader, in the background
        self.results = LatestWriter("results")   # a finished job's λ edits: results written after the answer
        self.networks = use_devices(networks, plan.cpus)
        self.watch = MemoryWatch(plan.memory_share, str(self.files.root / FAILURE_FILE))
        self._cancel = threading.Event()
        self._timings: dict[str, float] = {}
        self.loop: RenderLoop | None = None

    def pid(self) -> int:
        return os.getpid()

    def open(self) -> tuple[dict, int | None, bool, int]:
        """Load the scene and the last checkpoint: (effects report, iteration resumed from,
        whether a stop rule was already met, samples so far)."""
        record, files = self.plan.record, self.files
        state = self.checkpoint.load()
        root = files.bundle_dir if bundle_scene(record) else None
        self.loop = RenderLoop(job_spec(record, files.bundle_dir), self.networks, state=state, scene_root=root,
                               owned=range(*self.plan.owned))
        lam = files.load_lambda()  # newer than the checkpoint's copy
        if lam is not None and lam.shape == self.loop.state.lam_map.shape:
            self.loop.state.lam_map = lam
        resumed = state.iteration if state else None
        return self.loop.effects.as_record(), resumed, self.loop.done(), total_samples(self.loop.state.buffers)

    def cancel(self) -> None:
        """Stop within one wavefront chunk (the render phase raises IterationInterrupted)."""
        self._cancel.set()

    # -- the phases of one iteration ----------------------------------------------------------

    def render_phase(self, exchange: bool) -> ray.ObjectRef | None:
        """Render the owned frames; with `exchange`, a reference to them for the other shares
        (put here, so the frames go from worker to worker, never through the driver)."""
        self._timings = {}
        self.loop.render_step(self._timings, should_stop=self._cancel.is_set)
        return ray.put({f: self.loop.state.buffers[f] for f in self.loop.owned}) if exchange else None

    def denoise_phase(self, rendered: list) -> ray.ObjectRef | None:
        """Adopt the other shares' frames of this iteration, denoise the owned ones; a reference
        to their outputs when there are other shares to tell."""
        for buffers in ray.get(rendered):
            self.loop.adopt_rendered({f: b for f, b in buffers.items() if f not in self.loop.owned})
        self.loop.denoise_step(self._timings)
        return ray.put(self.loop.owned_outputs()) if rendered else None

    def finish_phase(self, outputs: list, seconds: float) -> IterationReport:
        for frames in ray.get(outputs):
            self.loop.adopt_denoised({f: o for f, o in frames.items() if f not in self.loop.owned})
        record = self.loop.finish_step(self._timings, seconds)
        report = IterationReport(record.iteration, record.spp_mean, record.predicted_error, record.stop_reason,
                                 total_samples(record.buffers), dict(self._timings))
        if self.plan.leader:
            # Off the render path: the copy now, the save on the checkpoint's thread while the
            # next iteration renders; the driver records this iteration only once
            # `checkpointed_through` says it landed (the order rule: checkpoint, previews, record).
            started = time.perf_counter()
            self.checkpoint.write_in_background(self.checkpoint.snapshot(self.loop.state))
            report.timings["io"] = report.timings.get("io", 0.0) + time.perf_counter() - started
            report.layers = preview_layers(self.loop, record)
        return report

    def checkpointed_through(self, iteration: int) -> None:
        """Return once iteration `iteration` is on disk; raise the save's failure if it failed."""
        self.checkpoint.wait_through(iteration)

    def progress(self) -> tuple[int, float]:
        """(finished iterations, mean spp) of the loop's state."""
        return self.loop.state.iteration, self.loop.state.spp_mean

    def save_results(self) -> None:
        """The result EXRs of the job's current state (the leader holds every frame)."""
        if self.loop is not None and self.loop.state.iteration > 0:
            self.files.save_results(self.loop.result_frames())

    def save_results_later(self) -> None:
        """save_results on a background thread, the newest edit's winning: the next λ edit runs
        meanwhile (this actor takes one call at a time; service.jobs.lambda_edits.Relambda says
        why no lock is needed)."""
        self.results.submit(self.plan.record.id, "results", self.save_results)

    def flush_results(self) -> None:
        """Return once the results asked for so far are written."""
        self.results.flush()

    # -- λ -----------------------------------------------------------------------------------

    def set_lambda(self, lam: np.ndarray) -> tuple[dict[int, np.ndarray], int, int, dict[str, float]]:
        """Re-denoise the owned frames from the cached features: (images, full, tail passes,
        seconds here: "denoise" the loop's re-denoise, "tail" the λ tail within it; the caller's
        wall time beyond "denoise" is the hop)."""
        done = self.loop.counted_set_lambda(lam)
        owned = {f: done.images[f] for f in self.loop.owned} if done.images else {}
        return owned, done.full_passes, done.tail_passes, done.timings
