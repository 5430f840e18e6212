"""The Ray backend writes checkpoints off the render path, and its driver records an iteration
only once that iteration's checkpoint is on disk: the Ray twins of
tests/service/test_checkpoint_writer.py, on a real local Ray runtime with real renders.

The leader actor lives in another process, so the slow or failing save and the event log come
from a test-side probe (tests/service/ray_probe/sitecustomize.py) that this module's runtime
loads into every Ray worker process."""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

import pytest

from required_components import import_component
import_component("ray")

from service.jobs.artifacts import JobFiles  # noqa: E402  (after the check: these import Ray's backend)
from service.jobs.ray_worker import RayJobWorker, RaySettings, start_local_ray  # noqa: E402
from service.jobs.store import COMPLETED, FAILED  # noqa: E402
from worker_jobs import run_tiny_job, store  # noqa: E402, F401  (store: a fixture)

PROBE = Path(__file__).parent / "ray_probe"
SLOW_SAVE_SECONDS = 2.0  # far longer than a 16² iteration takes, even on a loaded host


@pytest.fixture(scope="module")
def probe_dir(tmp_path_factory):
    """A local Ray runtime whose worker processes load the probe, logging to this folder."""
    folder = tmp_path_factory.mktemp("probe")
    saved = {name: os.environ.get(name) for name in ("PYTHONPATH", "RENDERLOOP_PROBE_DIR")}
    os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [str(PROBE), saved["PYTHONPATH"]]))
    os.environ["RENDERLOOP_PROBE_DIR"] = str(folder)
    try:
        runtime = start_local_ray(1)  # Ray's processes take the environment here, once
    finally:
        for name, value in saved.items():
            os.environ.pop(name, None) if value is None else os.environ.__setitem__(name, value)
    yield folder
    runtime.stop()


@pytest.fixture
def probe(probe_dir):
    """This test's events only, and the save mode it sets."""
    for name in ("events.jsonl", "save_mode"):
        (probe_dir / name).unlink(missing_ok=True)
    return probe_dir


@pytest.fixture
def worker(probe_dir, store, tiny_networks):
    w = RayJobWorker(store, tiny_networks, RaySettings(workers=1))
    w.start()
    yield w
    w.stop()


def events(probe: Path, what: str) -> dict[int, float]:
    """Wall-clock time of each iteration's `what` in the Ray worker processes (the first one)."""
    times: dict[int, float] = {}
    path = probe / "events.jsonl"
    for line in path.read_text().splitlines() if path.is_file() else []:
        at, name, iteration, _ = json.loads(line)
        if name == what:
            times.setdefault(iteration, at)
    return times


def test_the_leader_renders_the_next_iteration_while_its_checkpoint_is_written_and_the_record_follows_it(
        monkeypatch, probe, store, worker):
    (probe / "save_mode").write_text(f"slow {SLOW_SAVE_SECONDS}")
    recorded: dict[int, tuple[float, int]] = {}  # iteration → (when, the checkpoint's iteration then)
    record_iteration = store.record_iteration

    def checked_record(job_id, iteration, *args, **kwargs):
        on_disk = JobFiles(store.job_dir(job_id)).checkpoint.load()
        recorded[iteration] = (time.time(), on_disk.iteration if on_disk else 0)
        return record_iteration(job_id, iteration, *args, **kwargs)

    monkeypatch.setattr(store, "record_iteration", checked_record)
    done = run_tiny_job(store, worker, iterations=3)
    assert (done.state, done.iteration) == (COMPLETED, 3), done
    save_end, render_start = events(probe, "save_end"), events(probe, "render_start")
    assert sorted(save_end) == [1, 2, 3]
    for finished in (1, 2):  # iteration `finished` is being saved while the next one renders
        assert render_start[finished] < save_end[finished], (render_start, save_end)
    for iteration in (1, 2, 3):  # the record never runs ahead of its checkpoint
        assert recorded[iteration][1] >= iteration, recorded
        assert recorded[iteration][0] >= save_end[iteration], (recorded, save_end)
    # The render path did not wait for the disk: three slow saves overlapped two iterations' work.
    assert done.timings["io"] < SLOW_SAVE_SECONDS * 3, done.timings


@pytest.mark.parametrize("iterations", [1, 3])
def test_a_failed_checkpoint_save_in_the_leader_fails_the_job_with_the_saves_message(probe, store, worker,
                                                                                     iterations):
    (probe / "save_mode").write_text("fail")
    done = run_tiny_job(store, worker, iterations=iterations)
    assert done.state == FAILED, done
    assert "No space left on device" in (done.error or ""), done.error
    assert done.iteration == 0  # no record claims an iteration whose checkpoint was never written
    assert not JobFiles(store.job_dir(done.id)).checkpoint.exists()
