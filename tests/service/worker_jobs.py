"""Running one small job on a worker (either backend) against a real store, in tests that drive
the worker directly. Import `store` as a fixture: `from worker_jobs import run_tiny_job, store`."""
from __future__ import annotations

import time

import pytest

from service.jobs.record import JobRecord
from service.jobs.runner import JobRunner
from service.jobs.store import JobStore
from service.loop.spec import LoopSpec


@pytest.fixture
def store(tmp_path):
    s = JobStore(tmp_path / "data")
    yield s
    s.close()


def run_tiny_job(store: JobStore, worker: JobRunner, iterations: int, timeout: float = 180.0) -> JobRecord:
    """Submit a 16² cornell-box job of `iterations` iterations (4 spp first) and wait until it
    finished; its final record."""
    spec = LoopSpec(scene="cornell-box", width=16, height=16, spp_first=4, max_iterations=iterations)
    job_id = store.create(spec.to_stored(), spec.lam).id
    worker.submit(job_id)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        record = store.get(job_id)
        if record.finished:
            return record
        time.sleep(0.05)
    raise AssertionError(f"job did not finish within {timeout} s: {store.get(job_id)}")
