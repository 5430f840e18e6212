"""Which JobRunner runs the jobs: the thread backend (service.jobs.worker.JobWorker: loops in
threads of the API process) or the Ray backend (service.jobs.ray_worker.RayJobWorker: each job
in Ray actors, on this machine or a cluster). One interface: the API only calls the JobRunner
protocol's methods (service/jobs/runner.py)."""
from __future__ import annotations

from models.pretrained import Networks
from service.jobs.store import JobStore
from service.jobs.runner import JobRunner, NoObserver, WorkerObserver
from service.jobs.worker import JobWorker
from service.jobs.worker_settings import THREADS, WorkerSettings


def make_worker(store: JobStore, networks: Networks, settings: WorkerSettings = THREADS,
                observer: WorkerObserver = NoObserver()) -> JobRunner:
    if not settings.uses_ray:
        return JobWorker(store, networks, concurrency=settings.concurrency, observer=observer)
    # Imported here: Ray takes ~0.8 s to import, which thread-backend servers need not pay.
    from service.jobs.ray_worker import RaySettings, RayJobWorker, default_workers

    ray_settings = RaySettings(workers=settings.workers or default_workers(), address=settings.ray_address,
                               insecure=settings.insecure_ray)
    return RayJobWorker(store, networks, ray_settings, observer=observer)
