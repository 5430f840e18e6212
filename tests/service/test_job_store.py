"""The SQLite job store and the per-job artifacts folder, on a real file in tmp_path."""
from __future__ import annotations

import sqlite3
import threading

import numpy as np
import pytest

from service.jobs.artifacts import JobFiles, Preview
from service.jobs.latest import LatestWins
from service.jobs.store import CANCELED, COMPLETED, QUEUED, RUNNING, JobStore


@pytest.fixture
def store(tmp_path):
    s = JobStore(tmp_path)
    yield s
    s.close()


def test_create_and_read_back(store, tmp_path):
    record = store.create({"scene": "cornell-box", "width": 16}, lambda_value=2.0)
    assert len(record.id) == 32 and record.state == QUEUED
    again = store.get(record.id)
    assert again.spec == {"scene": "cornell-box", "width": 16}
    assert again.lambda_value == 2.0 and again.preview_version == 0
    assert store.job_dir(record.id).is_dir()
    journal = sqlite3.connect(tmp_path / "jobs.sqlite").execute("PRAGMA journal_mode").fetchone()[0]
    assert journal == "wal"


def test_state_transitions(store):
    job = store.create({}, None)
    assert store.claim(job.id) and not store.claim(job.id)  # only one worker wins
    store.record_iteration(job.id, 2, 32.0, 0.1, {"render": 1.5}, None)
    assert store.bump_preview_version(job.id) == 1
    assert store.bump_preview_version(job.id) == 2
    store.finish(job.id, COMPLETED, stop_reason="max_iterations")
    done = store.get(job.id)
    assert (done.state, done.iteration, done.spp, done.stop_reason) == (COMPLETED, 2, 32.0, "max_iterations")
    assert done.started_at is not None and done.finished_at >= done.started_at
    assert done.timings == {"render": 1.5}


def test_cancel_only_wins_while_queued(store):
    queued, running = store.create({}, None), store.create({}, None)
    store.claim(running.id)
    assert store.cancel_if_queued(queued.id) and store.get(queued.id).state == CANCELED
    assert not store.cancel_if_queued(running.id) and store.get(running.id).state == RUNNING


def test_restart_requeues_running_jobs(tmp_path):
    first = JobStore(tmp_path)
    job = first.create({}, None)
    first.claim(job.id)
    first.close()  # the process "dies" with the job marked running
    second = JobStore(tmp_path)
    assert second.requeue_running() == [job.id]
    assert second.get(job.id).state == QUEUED and second.ids_in_state(QUEUED) == [job.id]
    second.close()


def test_list_is_newest_first_and_filters_by_state(store):
    a, b = store.create({}, None), store.create({}, None)
    store.claim(b.id)
    assert [r.id for r in store.list()] == [b.id, a.id]
    assert [r.id for r in store.list(state=RUNNING)] == [b.id]


def test_artifacts_roundtrip(tmp_path):
    files = JobFiles(tmp_path / "job")
    lam = np.full((4, 6), 3.0, dtype=np.float32)
    files.save_lambda(lam)
    np.testing.assert_array_equal(files.load_lambda(), lam)
    assert files.load_preview(0) is None
    files.save_preview(0, Preview(version=7, layers={"denoised": np.ones((4, 6, 3), np.float32), "error": None}))
    preview = files.load_preview(0)
    assert preview.version == 7 and preview.layers["error"] is None
    assert preview.layers["denoised"].shape == (4, 6, 3)
    assert not files.has_checkpoint()


def test_latest_wins_skips_superseded_requests():
    applied: list[int] = []
    gate = threading.Event()

    def apply(value: int) -> int:
        gate.wait(5)
        applied.append(value)
        return value * 10

    box = LatestWins(apply)
    tickets = [box.submit(v) for v in range(5)]  # the first is in flight, the rest pile up
    gate.set()
    results = [box.wait(t, timeout=5) for t in tickets]
    assert applied[-1] == 4 and len(applied) <= 2  # 1..3 were replaced before they ran
    assert results[-1] == 40 and all(r in (0, 40) for r in results)


def test_latest_wins_drops_a_request_ordered_before_one_already_seen():
    applied: list[str] = []
    box = LatestWins(lambda value: applied.append(value) or value)
    newer = box.submit("third", order=3)
    assert box.wait(newer, timeout=5) == "third"
    late = box.submit("second", order=2)  # issued before "third", arrived after it
    assert box.wait(late, timeout=5) == "third" and applied == ["third"]
    assert box.wait(box.submit("unordered"), timeout=5) == "unordered"  # no order: arrival decides
    assert box.wait(box.submit("fourth", order=4), timeout=5) == "fourth"


def test_latest_wins_reports_failures():
    def apply(value: int) -> int:
        raise ValueError(f"bad {value}")

    box = LatestWins(apply)
    with pytest.raises(ValueError, match="bad 1"):
        box.wait(box.submit(1), timeout=5)
