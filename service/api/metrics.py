"""GET /metrics: what the service does, in Prometheus text format.

Each app owns its CollectorRegistry (never prometheus-client's global one), so two apps in one
process — tests, a benchmark beside a server — count separately. The worker reports
iterations and λ edits through its observer hook (service.jobs.runner.WorkerObserver); the
job-state gauge is read from the store at scrape time, so it is right after a restart too.
"""
from __future__ import annotations

from typing import Iterator

from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, Counter, Histogram, generate_latest
from prometheus_client.core import GaugeMetricFamily, Metric

from service.jobs.store import STATES, JobStore

PREFIX = "renderloop_"
STAGES = ("render", "denoise", "error", "allocate")  # the stages IterationRecord.timings holds
# Seconds: a 32² test iteration takes milliseconds, a 2048² frame minutes.
STAGE_BUCKETS = (0.001, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 120.0, 300.0)
# A λ edit re-runs only the denoiser's tail: tens of milliseconds, seconds for big frames.
LAMBDA_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)
MEDIA_TYPE = CONTENT_TYPE_LATEST


class JobStateCollector:
    """`renderloop_jobs{state=…}`: how many jobs are in each state, counted when scraped."""

    def __init__(self, store: JobStore) -> None:
        self.store = store

    def _family(self) -> GaugeMetricFamily:
        return GaugeMetricFamily(PREFIX + "jobs", "Jobs in each state", labels=["state"])

    def describe(self) -> Iterator[Metric]:
        yield self._family()  # names only: registering must not query the store

    def collect(self) -> Iterator[Metric]:
        family = self._family()
        for state in STATES:
            family.add_metric([state], len(self.store.ids_in_state(state)))
        yield family


class ServiceMetrics:
    """The app's metrics; a WorkerObserver for the job worker."""

    def __init__(self, store: JobStore) -> None:
        self.registry = CollectorRegistry()
        self.stage_seconds = Histogram(
            PREFIX + "iteration_stage_seconds", "Seconds one loop iteration spent in each stage",
            ["stage"], buckets=STAGE_BUCKETS, registry=self.registry)
        self.lambda_seconds = Histogram(
            PREFIX + "lambda_edit_seconds", "Seconds from a λ edit's request to the preview that shows it",
            buckets=LAMBDA_BUCKETS, registry=self.registry)
        self.samples = Counter(PREFIX + "samples_rendered", "Samples rendered, all jobs and frames",
                               registry=self.registry)
        self.iterations = Counter(PREFIX + "iterations", "Loop iterations finished", registry=self.registry)
        for stage in STAGES:
            self.stage_seconds.labels(stage=stage)  # every stage listed from the start, at zero
        self.registry.register(JobStateCollector(store))

    def iteration_finished(self, timings: dict[str, float], samples: int) -> None:
        for stage in STAGES:
            if stage in timings:
                self.stage_seconds.labels(stage=stage).observe(float(timings[stage]))
        self.samples.inc(max(0, samples))
        self.iterations.inc()

    def lambda_applied(self, seconds: float) -> None:
        self.lambda_seconds.observe(seconds)

    def exposition(self) -> bytes:
        return generate_latest(self.registry)
