"""A λ edit is answered once its map is on disk; its preview and result files follow in the
background (service/jobs/lambda_edits.py). A process killed in between leaves a finished job's
files one edit behind its saved map: the next process must show the answered edit. The worker
runs in this process against a real store, real renders and the shipped networks; the crash is
played by putting the files from before the edit back (what a kill -9 before the background
write leaves) and starting a second worker on the same store, as a restarted server does."""
from __future__ import annotations

import shutil

import numpy as np
import pytest

from models.pretrained import load_networks
from service.exr import read_exr
from service.jobs.worker import JobWorker
from worker_jobs import run_tiny_job, store  # noqa: F401  (store: a fixture)


@pytest.fixture(scope="module")
def shipped_networks():
    return load_networks()   # λ changes their image (a fresh network's λ module is inert)


@pytest.fixture
def edit_lost_in_a_crash(store, shipped_networks, tmp_path):  # noqa: F811
    """A finished job whose λ map was saved (λ = 9 on the left half) but whose preview and result
    still show the λ it finished with; returns (job id, the saved map, the result before)."""
    worker = JobWorker(store, shipped_networks)
    worker.start()
    job_id = run_tiny_job(store, worker, iterations=1).id
    files = worker.files(job_id)
    before = tmp_path / "before"
    shutil.copytree(files.root / "previews", before / "previews")
    shutil.copytree(files.root / "result", before / "result")
    lam = np.ones((16, 16), np.float32)
    lam[:, :8] = 9.0
    worker.set_lambda(job_id, lam)
    worker.stop()   # every answered write lands ...
    for name in ("previews", "result"):   # ... and the crash takes them back
        shutil.rmtree(files.root / name)
        shutil.copytree(before / name, files.root / name)
    return job_id, lam, read_exr(files.result_path(0))


def test_after_a_crash_the_first_result_read_shows_the_last_answered_edit(store, shipped_networks,  # noqa: F811
                                                                         edit_lost_in_a_crash):
    job_id, lam, before = edit_lost_in_a_crash
    assert not np.array_equal(before.lam, lam)   # the planted crash: the file is one edit behind
    restarted = JobWorker(store, shipped_networks)
    restarted.start()
    try:
        result = read_exr(restarted.result_path(job_id, 0))
        np.testing.assert_array_equal(result.lam, lam)
        assert not np.array_equal(result.color, before.color)   # re-denoised, not just relabelled
    finally:
        restarted.stop()


def test_after_a_crash_the_first_preview_read_shows_the_last_answered_edit(store, shipped_networks,  # noqa: F811
                                                                          edit_lost_in_a_crash):
    job_id, lam, _ = edit_lost_in_a_crash
    restarted = JobWorker(store, shipped_networks)
    restarted.start()
    try:
        preview = restarted.load_preview(job_id, 0)
        np.testing.assert_array_equal(preview.layers["lambda"], lam)
        np.testing.assert_array_equal(read_exr(restarted.result_path(job_id, 0)).lam, lam)
    finally:
        restarted.stop()


def test_a_job_whose_files_match_its_saved_map_is_not_denoised_again(store, shipped_networks):  # noqa: F811
    worker = JobWorker(store, shipped_networks)
    worker.start()
    job_id = run_tiny_job(store, worker, iterations=1).id
    worker.set_lambda(job_id, np.full((16, 16), 3.0, np.float32), 3.0)
    worker.stop()
    restarted = JobWorker(store, shipped_networks)
    restarted.start()
    try:
        version = store.get(job_id).preview_version
        restarted.result_path(job_id, 0)
        restarted.load_preview(job_id, 0)
        assert store.get(job_id).preview_version == version   # no edit was applied again
    finally:
        restarted.stop()
