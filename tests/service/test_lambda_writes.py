"""A λ edit answers before its files are written (service/jobs/latest_writer.py): what the
answer promises must still hold. The worker runs in this process against a real store with real
renders and the shipped networks; the background writes are slowed down (a sleep before each
preview and result write) so the checks run while they are still pending, whatever the host's
load: a GET right after the PUT shows the edit, and a stop lands every answered edit on disk."""
from __future__ import annotations

import threading
import time

import httpx
import numpy as np
import pytest

from models.pretrained import load_networks
from service.jobs.artifacts import JobFiles
from service.jobs.latest_writer import LatestWriter
from service.jobs.worker import JobWorker
from service.exr import read_exr
from service_harness import finished, wait_for
from worker_jobs import run_tiny_job, store  # noqa: F401  (store: a fixture)

WRITE_DELAY = 1.5   # seconds each background preview/result write sleeps first
BACKGROUND_THREAD = "job-writes"   # service.jobs.previews.PreviewPublisher's writer


@pytest.fixture(scope="module")
def shipped_networks():
    return load_networks()   # λ changes their image (a fresh network's λ module is inert)


@pytest.fixture
def slow_writes(monkeypatch):
    """Each preview and result write of the background writer sleeps first; counts those that landed."""
    landed = {"previews": 0, "results": 0}
    save_preview, save_results = JobFiles.save_preview, JobFiles.save_results

    def slow(kind, save):
        def write(self, *args):
            in_background = threading.current_thread().name == BACKGROUND_THREAD
            if in_background:
                time.sleep(WRITE_DELAY)
            save(self, *args)
            landed[kind] += in_background
        return write

    monkeypatch.setattr(JobFiles, "save_preview", slow("previews", save_preview))
    monkeypatch.setattr(JobFiles, "save_results", slow("results", save_results))
    return landed


@pytest.fixture
def finished_job(store, shipped_networks):  # noqa: F811
    worker = JobWorker(store, shipped_networks)
    worker.start()
    record = run_tiny_job(store, worker, iterations=1)
    yield worker, record.id
    worker.stop()


def test_the_preview_and_the_result_right_after_an_edit_show_it(finished_job, slow_writes):
    worker, job_id = finished_job
    files = worker.files(job_id)
    before = read_exr(files.result_path(0))
    applied = worker.set_lambda(job_id, np.full((16, 16), 10.0, np.float32), 10.0)
    assert slow_writes == {"previews": 0, "results": 0}   # answered before its files were written
    preview = worker.load_preview(job_id, 0)
    assert preview.version == applied.version and np.all(preview.layers["lambda"] == 10.0)
    assert files.load_preview(0).version < applied.version   # the file still holds the older one
    result = read_exr(worker.result_path(job_id, 0))       # waits for the edit's result
    assert np.all(result.lam == 10.0) and not np.array_equal(result.color, before.color)
    np.testing.assert_array_equal(result.color, preview.layers["denoised"])


def test_a_stop_right_after_an_edit_lands_its_preview_and_result(store, shipped_networks, slow_writes):  # noqa: F811
    worker = JobWorker(store, shipped_networks)
    worker.start()
    job_id = run_tiny_job(store, worker, iterations=1).id
    lam = np.ones((16, 16), np.float32)
    lam[:, :8] = 7.0
    applied = worker.set_lambda(job_id, lam)
    worker.stop()   # what the server's shutdown calls
    files = JobFiles(store.job_dir(job_id))
    assert slow_writes == {"previews": 1, "results": 1}
    np.testing.assert_array_equal(files.load_lambda(), lam)
    assert files.load_preview(0).version == applied.version
    np.testing.assert_array_equal(read_exr(files.result_path(0)).lam, lam)


def test_a_burst_writes_only_the_newest_edit_once_the_one_in_flight_is_done(finished_job, slow_writes):
    worker, job_id = finished_job
    versions = [worker.set_lambda(job_id, np.full((16, 16), value, np.float32), value).version
                for value in (2.0, 3.0, 4.0, 5.0)]
    worker.lambdas.flush(job_id)
    files = worker.files(job_id)
    assert files.load_preview(0).version == versions[-1]
    assert np.all(read_exr(files.result_path(0)).lam == 5.0)
    # the first edit's writes were in flight when the others came; of those only the last is written
    assert slow_writes["previews"] <= 2 and slow_writes["results"] <= 2


def test_the_writer_keeps_the_newest_write_per_key_and_flushes_per_job():
    writer = LatestWriter("test-writer")
    gate, done = threading.Event(), []
    writer.submit("a", "x", gate.wait)             # occupies the thread
    for value in (1, 2, 3):
        writer.submit("a", "y", lambda value=value: done.append(("a", value)))
    writer.submit("b", "y", lambda: done.append(("b", 0)))
    assert not writer.flush("b", timeout=0.2)      # queued behind the running write
    gate.set()
    assert writer.flush("a", timeout=30) and writer.flush(timeout=30)
    assert done == [("a", 3), ("b", 0)]


def test_a_failed_write_is_logged_and_the_next_one_still_runs(caplog):
    writer = LatestWriter("test-writer")
    done = []
    writer.submit("a", "x", lambda: 1 / 0)
    writer.submit("a", "y", lambda: done.append(1))
    assert writer.flush(timeout=30)
    assert done == [1] and "writing its x failed" in caplog.text


def exr_of(response, tmp_path, name: str):
    assert response.status_code == 200, response.text
    (tmp_path / name).write_bytes(response.content)
    return read_exr(tmp_path / name)


@pytest.mark.slow   # two server starts and a render (~40 s on the loaded host); the in-process stop test above is the fast one
def test_a_server_stopped_right_after_a_put_restarts_with_the_edit(start_server, tmp_path):
    """Over HTTP, end to end: PUT λ, SIGTERM at once (the server's graceful stop), a new server
    on the same data dir serves the edit's λ, preview and result."""
    first = start_server()
    with httpx.Client(base_url=first.url, timeout=120) as client:
        job_id = client.post("/jobs", json={"scene": "cornell-box", "width": 48, "height": 32,
                                            "max_iterations": 1}).json()["id"]
        assert wait_for(client, job_id, finished)["state"] == "completed"
        before = exr_of(client.get(f"/jobs/{job_id}/result.exr"), tmp_path, "before.exr")
        rects = {"rects": [{"x": 0, "y": 0, "w": 24, "h": 32, "value": 10.0}]}
        applied = client.put(f"/jobs/{job_id}/lambda", json=rects)
        assert applied.status_code == 200, applied.text
    first.stop()
    expected = np.ones((32, 48), np.float32)
    expected[:, :24] = 10.0
    second = start_server(first.data_dir)
    with httpx.Client(base_url=second.url, timeout=120) as client:
        result = exr_of(client.get(f"/jobs/{job_id}/result.exr"), tmp_path, "after.exr")
        np.testing.assert_array_equal(result.lam, expected)
        assert not np.array_equal(result.color, before.color)
        preview = client.get(f"/jobs/{job_id}/preview", params={"layer": "lambda", "format": "exr"})
        assert preview.headers["x-preview-version"] == str(applied.json()["version"])
        np.testing.assert_array_equal(exr_of(preview, tmp_path, "lambda.exr").lam, expected)


def test_edited_previews_stay_in_memory_for_the_last_jobs_and_never_before_their_files(store, monkeypatch):  # noqa: F811
    """A λ edit's frames are the only copy of their version until written; once written, the
    newest EDITED_JOBS_KEPT jobs keep them; an iteration's newer files take their place."""
    from service.jobs.previews import EDITED_JOBS_KEPT, PreviewPublisher
    from service.loop.spec import LoopSpec

    publisher = PreviewPublisher(store)
    spec = LoopSpec(scene="cornell-box", width=4, height=4)
    jobs = [store.create(spec.to_stored(), spec.lam).id for _ in range(EDITED_JOBS_KEPT + 2)]
    frames = lambda value: [{"denoised": np.full((4, 4, 3), value, np.float32), "noisy": None}]   # noqa: E731
    gate = threading.Event()
    publisher.writes.submit("someone", "else", gate.wait)   # holds the writer: nothing lands yet
    for i, job in enumerate(jobs):
        publisher.publish_later(job, JobFiles(store.job_dir(job)), frames(i))
    assert all(publisher.load(job, JobFiles(store.job_dir(job)), 0) is not None for job in jobs)   # none written, none dropped
    gate.set()
    publisher.writes.flush()
    kept = [job for job in jobs if job in publisher._edited]
    assert kept == jobs[-EDITED_JOBS_KEPT:]
    oldest = JobFiles(store.job_dir(jobs[0]))
    assert float(publisher.load(jobs[0], oldest, 0).layers["denoised"][0, 0, 0]) == 0.0   # from its file now
    newest = JobFiles(store.job_dir(jobs[-1]))
    version = publisher.publish(jobs[-1], newest, frames(9.0))   # an iteration, written at once
    assert jobs[-1] not in publisher._edited
    assert publisher.load(jobs[-1], newest, 0).version == version
