"""Checkpoints and previews are written off the render path (service/jobs/checkpoint_writer.py):
the thread worker with a real store and real renders, the checkpoint save made slow or failing."""
from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from service.jobs import checkpoint_format
from service.jobs.store import COMPLETED, FAILED
from service.jobs.worker import JobWorker
from service.loop.loop import RenderLoop
from worker_jobs import run_tiny_job, store  # noqa: F401  (store: a fixture)

ROOT = Path(__file__).resolve().parents[2]
SLOW_SAVE_SECONDS = 2.0  # far longer than a 16² iteration takes, even on a loaded host


class Events:
    """Timestamped (what, iteration) events from the render, writer and store threads."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.items: list[tuple[float, str, int]] = []

    def add(self, what: str, iteration: int) -> None:
        with self._lock:
            self.items.append((time.monotonic(), what, iteration))

    def times(self, what: str) -> dict[int, float]:
        return {iteration: t for t, w, iteration in self.items if w == what}


@pytest.fixture
def events(monkeypatch, store) -> Events:
    """Saves take SLOW_SAVE_SECONDS; saves, renders and iteration records are timestamped."""
    log = Events()
    save, render, record_iteration = checkpoint_format.write_state, RenderLoop.render_step, store.record_iteration

    def slow_save(state, directory):
        log.add("save_start", state.iteration)
        time.sleep(SLOW_SAVE_SECONDS)
        path = save(state, directory)
        log.add("save_end", state.iteration)
        return path

    def timed_render(self, timings, should_stop=lambda: False):
        log.add("render_start", self.state.iteration)  # the iteration about to be rendered, 0-based
        return render(self, timings, should_stop)

    def recorded(job_id, iteration, *args, **kwargs):
        log.add("record", iteration)
        return record_iteration(job_id, iteration, *args, **kwargs)

    monkeypatch.setattr(checkpoint_format, "write_state", slow_save)
    monkeypatch.setattr(RenderLoop, "render_step", timed_render)
    monkeypatch.setattr(store, "record_iteration", recorded)
    return log


def test_the_next_iteration_renders_while_the_checkpoint_is_written(store, tiny_networks, events):
    worker = JobWorker(store, tiny_networks)
    try:
        done = run_tiny_job(store, worker, iterations=3)
    finally:
        worker.stop()
    assert (done.state, done.iteration) == (COMPLETED, 3)
    save_end = events.times("save_end")
    render_start, record = events.times("render_start"), events.times("record")
    assert sorted(save_end) == [1, 2, 3]
    for finished in (1, 2):  # iteration `finished` is being written while the next one renders
        assert render_start[finished] < save_end[finished], events.items
    for iteration in (1, 2, 3):  # the record never runs ahead of the checkpoint
        assert record[iteration] >= save_end[iteration], events.items
    # Rendering did not wait for the disk: three slow saves overlapped two iterations' work.
    assert done.timings["io"] < SLOW_SAVE_SECONDS * 3, done.timings
    assert checkpoint_format.read_state(worker.files(done.id).state_dir).iteration == 3  # the last write landed


@pytest.mark.parametrize("iterations", [1, 3])
def test_a_failed_checkpoint_write_fails_the_job_with_the_writes_message(monkeypatch, store, tiny_networks,
                                                                         iterations):
    def full_disk(state, directory):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(checkpoint_format, "write_state", full_disk)
    worker = JobWorker(store, tiny_networks)
    try:
        done = run_tiny_job(store, worker, iterations=iterations)
    finally:
        worker.stop()
    assert done.state == FAILED, done
    assert "No space left on device" in (done.error or ""), done.error
    assert done.iteration == 0  # no record claims an iteration whose checkpoint was never written
    assert not worker.files(done.id).checkpoint.exists()


def test_a_write_submitted_while_the_interpreter_exits_runs_on_the_callers_thread(tmp_path):
    """A SIGTERM'd server's render thread may finish its iteration after the main thread is gone;
    concurrent.futures then refuses new work, and the checkpoint must still land (the requeued job
    resumes from it) instead of failing the job with a traceback."""
    written = tmp_path / "written"
    script = f"""
import threading, time
from pathlib import Path
from service.jobs.checkpoint_writer import CheckpointWriter

def render_thread():
    writer = CheckpointWriter("exiting")
    time.sleep(1.0)  # the main thread has returned meanwhile: the interpreter is exiting
    writer.submit(lambda: Path({str(written)!r}).write_text(threading.current_thread().name))
    writer.flush()

threading.Thread(target=render_thread, name="render").start()
"""
    done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr
    assert written.read_text() == "render"
