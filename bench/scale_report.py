"""`renderloop bench --scale`: the Ray backend's scaling on this machine (docs/scale.md).

All in one run, on one local Ray runtime with two CPUs, with the shipped networks:
(a) throughput of 8 small jobs with 1 vs 2 workers, and the ratio;
(b) per-iteration overhead of the Ray path vs the in-process thread backend: an iteration's wall
    time (between two recorded iterations) minus its compute stages (allocate, render, denoise,
    error), median over the iterations after the first;
(c) a 5-frame sequence on 1 vs 2 workers (its frames shared between the workers' actors).
"""
from __future__ import annotations

import statistics
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import ray

from bench.common import fill, fmt, pinned_torch_threads, provenance
from models.pretrained import Networks, load_networks
from service.jobs.ray_worker import RayJobWorker, RaySettings, start_local_ray
from service.jobs.store import COMPLETED, JobStore
from service.jobs.worker import JobWorker
from service.loop.spec import LoopSpec
from service.render.runtime import active_variant

RAY_CPUS = 2
COMPUTE_STAGES = ("allocate", "render", "denoise", "error")
THROUGHPUT_JOBS = 8
THROUGHPUT_JOB = LoopSpec(scene="cornell-box", width=128, height=128, spp_first=16, max_iterations=4)
OVERHEAD_JOB = LoopSpec(scene="cornell-box", width=32, height=32, spp_first=4, max_iterations=7)
SEQUENCE_JOB = LoopSpec(scene="cornell-box-orbit", width=96, height=96, frames=5, spp_first=16, max_iterations=4)
JOB_TIMEOUT_SECONDS = 1800.0


class TimedStore(JobStore):
    """A job store that notes when each iteration was recorded and its cumulative timings."""

    def __init__(self, data_dir: Path) -> None:
        super().__init__(data_dir)
        self.marks: dict[str, list[tuple[float, dict[str, float]]]] = {}

    def record_iteration(self, job_id, iteration, spp, predicted_error, timings, stop_reason=None) -> None:
        super().record_iteration(job_id, iteration, spp, predicted_error, timings, stop_reason)
        self.marks.setdefault(job_id, []).append((time.perf_counter(), dict(timings)))

    def overheads(self, job_id: str) -> list[float]:
        """Per iteration after the first: wall time between records minus its compute stages."""
        marks = self.marks[job_id]
        result = []
        for (t0, s0), (t1, s1) in zip(marks, marks[1:]):
            compute = sum(s1.get(k, 0.0) - s0.get(k, 0.0) for k in COMPUTE_STAGES)
            result.append(t1 - t0 - compute)
        return result

    def iteration_walls(self, job_id: str) -> list[float]:
        marks = self.marks[job_id]
        return [t1 - t0 for (t0, _), (t1, _) in zip(marks, marks[1:])]


@dataclass
class Run:
    """Jobs run to the end on one worker set-up."""

    label: str
    seconds: float
    store: TimedStore
    ids: list[str] = field(default_factory=list)


def run_jobs(label: str, worker_for: Callable[[JobStore], JobWorker], specs: list[LoopSpec]) -> Run:
    store = TimedStore(Path(tempfile.mkdtemp(prefix="renderloop-scale-")))
    worker = worker_for(store)
    worker.start()
    try:
        started = time.perf_counter()
        ids = []
        for spec in specs:
            ids.append(store.create(spec.to_stored(), spec.lam).id)
            worker.submit(ids[-1])
        deadline = time.monotonic() + JOB_TIMEOUT_SECONDS
        while not all(store.get(i).finished for i in ids):
            if time.monotonic() > deadline:
                raise TimeoutError(f"{label}: jobs not finished within {JOB_TIMEOUT_SECONDS:.0f} s")
            time.sleep(0.05)
        seconds = time.perf_counter() - started
    finally:
        worker.stop()
    failed = [store.get(i) for i in ids if store.get(i).state != COMPLETED]
    if failed:
        raise RuntimeError(f"{label}: {len(failed)} job(s) did not complete: {failed[0].error}")
    return Run(label, seconds, store, ids)


def ray_worker(networks: Networks, workers: int):
    # A stop() of a worker that did not start Ray leaves the runtime up for the next run.
    return lambda store: RayJobWorker(store, networks, RaySettings(workers=workers))


def thread_worker(networks: Networks):
    return lambda store: JobWorker(store, networks, concurrency=1)


@dataclass
class ScaleResults:
    throughput: dict[int, Run]
    overhead_threads: Run
    overhead_ray: Run
    sequence: dict[int, Run]


def measure(networks: Networks) -> ScaleResults:
    start_local_ray(RAY_CPUS)
    try:
        throughput = {w: run_jobs(f"{THROUGHPUT_JOBS} jobs, {w} worker(s)", ray_worker(networks, w),
                                  [THROUGHPUT_JOB] * THROUGHPUT_JOBS) for w in (1, 2)}
        with pinned_torch_threads(1):  # as in a worker (one CPU each)
            overhead_threads = run_jobs("in-process", thread_worker(networks), [OVERHEAD_JOB])
        overhead_ray = run_jobs("Ray, 1 worker", ray_worker(networks, 1), [OVERHEAD_JOB])
        sequence = {w: run_jobs(f"5 frames, {w} worker(s)", ray_worker(networks, w), [SEQUENCE_JOB]) for w in (1, 2)}
    finally:
        ray.shutdown()
    return ScaleResults(throughput, overhead_threads, overhead_ray, sequence)


def job_seconds(run: Run) -> tuple[float, float]:
    """Mean per job: wall from its start to its end, and its compute stages."""
    records = [run.store.get(i) for i in run.ids]
    walls = [r.finished_at - r.started_at for r in records]
    compute = [sum(r.timings.get(k, 0.0) for k in COMPUTE_STAGES) for r in records]
    return statistics.mean(walls), statistics.mean(compute)


def _median_ms(values: list[float]) -> str:
    return fmt(1000 * statistics.median(values), ".1f") if values else "n/a"


def _spec_line(spec: LoopSpec) -> str:
    return (f"`{spec.scene}` {spec.width}x{spec.height}, {spec.frames} frame(s), {spec.spp_first} spp first, "
            f"{spec.max_iterations} iterations")


def write_scale_report(results: ScaleResults, out: Path) -> Path:
    one, two = results.throughput[1], results.throughput[2]
    per_minute = {w: 60 * THROUGHPUT_JOBS / run.seconds for w, run in results.throughput.items()}
    threads, on_ray = results.overhead_threads, results.overhead_ray
    over_threads = threads.store.overheads(threads.ids[0])
    over_ray = on_ray.store.overheads(on_ray.ids[0])
    seq1, seq2 = results.sequence[1], results.sequence[2]
    walls1, walls2 = (run.store.iteration_walls(run.ids[0]) for run in (seq1, seq2))
    out.mkdir(parents=True, exist_ok=True)
    path = out / "scale.md"
    path.write_text(fill(
        "scale.md", provenance=provenance(variant=active_variant()), cpus=RAY_CPUS, jobs=THROUGHPUT_JOBS,
        throughput_job=_spec_line(THROUGHPUT_JOB), overhead_job=_spec_line(OVERHEAD_JOB),
        sequence_job=_spec_line(SEQUENCE_JOB),
        one_s=fmt(one.seconds, ".1f"), two_s=fmt(two.seconds, ".1f"),
        one_rate=fmt(per_minute[1], ".1f"), two_rate=fmt(per_minute[2], ".1f"),
        ratio=fmt(per_minute[2] / per_minute[1], ".2f"),
        one_job=fmt(job_seconds(one)[0], ".1f"), two_job=fmt(job_seconds(two)[0], ".1f"),
        one_compute=fmt(job_seconds(one)[1], ".1f"), two_compute=fmt(job_seconds(two)[1], ".1f"),
        threads_ms=_median_ms(over_threads), ray_ms=_median_ms(over_ray),
        delta_ms=fmt(1000 * (statistics.median(over_ray) - statistics.median(over_threads)), ".1f"),
        threads_wall=fmt(threads.seconds, ".1f"), ray_wall=fmt(on_ray.seconds, ".1f"),
        seq1_s=fmt(seq1.seconds, ".1f"), seq2_s=fmt(seq2.seconds, ".1f"),
        seq_ratio=fmt(seq1.seconds / seq2.seconds, ".2f"),
        seq1_iter=_median_ms(walls1), seq2_iter=_median_ms(walls2)))
    return path


def run_scale_report(out: Path, weights_dir: Path | None = None) -> Path:
    return write_scale_report(measure(load_networks(weights_dir)), out)
