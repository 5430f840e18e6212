"""Retention: old finished jobs and the oldest ones over the disk cap go; unfinished ones stay
(the sweeps run on both job databases, SQLite and PostgreSQL: conftest's db_url)."""
from __future__ import annotations

import time

import httpx

from service.jobs.retention import Retention, folder_bytes, sweep
from service.jobs.store import COMPLETED, FAILED, JobStore
from service.loop.spec import LoopSpec
from service_harness import Server


def finished_job(store: JobStore, state: str = COMPLETED, size: int = 0) -> str:
    record = store.create({}, None)
    store.claim(record.id)
    store.finish(record.id, state)
    (store.job_dir(record.id) / "result.bin").write_bytes(b"x" * size)
    return record.id


def test_finished_jobs_older_than_keep_days_are_removed_and_unfinished_ones_kept(tmp_path, db_url):
    store = JobStore(tmp_path, db_url)
    old, failed = finished_job(store), finished_job(store, FAILED)
    queued = store.create({}, None).id
    running = store.create({}, None).id
    store.claim(running)
    removed = sweep(store, Retention(keep_days=1.0), now=time.time() + 2 * 86400)
    assert set(removed) == {old, failed}
    assert store.get(old) is None and not store.job_dir(old).exists()
    assert store.get(queued) is not None and store.get(running) is not None


def test_over_the_disk_cap_the_oldest_finished_jobs_go_first(tmp_path, db_url):
    store = JobStore(tmp_path, db_url)
    first, second, third = (finished_job(store, size=100_000) for _ in range(3))
    cap = folder_bytes(tmp_path) - 150_000  # two of the three must go
    removed = sweep(store, Retention(max_disk_bytes=cap))
    assert removed == [first, second] and store.get(third) is not None
    assert folder_bytes(tmp_path) <= cap


def test_no_policy_removes_nothing(tmp_path, db_url):
    store = JobStore(tmp_path, db_url)
    finished_job(store)
    assert sweep(store, Retention(), now=time.time() + 10**9) == []


def test_a_server_started_with_keep_days_removes_finished_jobs_past_it(tmp_path):
    # The finished job is written into the data dir's store as a server leaves one (its spec, its
    # folder with a result file): a first server rendering it cost a server start and a render.
    store = JobStore(tmp_path / "data")
    spec = LoopSpec(scene="cornell-box", width=8, height=8, max_iterations=1, denoise=False, allocator="uniform")
    job_id = store.create(spec.to_stored(), spec.lam).id
    store.claim(job_id)
    store.finish(job_id, COMPLETED, stop_reason="max_iterations")
    job_dir = store.job_dir(job_id)
    (job_dir / "result.exr").write_bytes(b"x" * 1000)
    store.close()
    time.sleep(1.5)  # older than one second by the time the server sweeps
    server = Server(tmp_path / "data", tmp_path / "server.log", env={"RENDERLOOP_KEEP_DAYS": str(1 / 86400)}).start()
    try:
        with httpx.Client(base_url=server.url, timeout=60) as client:
            deadline = time.monotonic() + 30
            while client.get(f"/jobs/{job_id}").status_code != 404 and time.monotonic() < deadline:
                time.sleep(0.2)
            assert client.get(f"/jobs/{job_id}").status_code == 404
        assert not job_dir.exists() and job_dir.parent.is_dir()
    finally:
        server.stop()
