"""The Ray backend on a real local Ray runtime with two workers: real actors in their own
processes, real Mitsuba renders at tiny sizes, the real job store. The tests drive the worker
(service.jobs.ray_worker.RayJobWorker) directly, so they can find and kill its processes; a served
app on uvicorn with RENDERLOOP_WORKERS=2 running two jobs at once is in test_ray_seal.py (whose
Ray-backed server it shares)."""
from __future__ import annotations

import os
import signal
import sqlite3
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from required_components import import_component
ray = import_component("ray")

from service.exr import read_exr  # noqa: E402  (after the check: these import Ray's backend)
from service.jobs import ray_worker  # noqa: E402
from service.jobs.ray_worker import (CANCEL_GRACE_SECONDS, RayJobWorker, RaySettings, shares,  # noqa: E402
                                     start_local_ray)
from service.jobs.store import CANCELED, COMPLETED, FAILED, QUEUED, RUNNING, JobRecord, JobStore  # noqa: E402
from service.loop.loop import RenderLoop  # noqa: E402
from service.loop.spec import LoopSpec  # noqa: E402

WORKERS = 2


@pytest.fixture(scope="module")
def ray_runtime():
    """One local Ray runtime (two CPUs: two workers) for the module; starting one costs ~8 s."""
    runtime = start_local_ray(WORKERS)
    yield
    runtime.stop()


@pytest.fixture
def store(tmp_path):
    s = JobStore(tmp_path / "data")
    yield s
    s.close()


@pytest.fixture
def worker(ray_runtime, store, tiny_networks):
    w = RayJobWorker(store, tiny_networks, RaySettings(workers=WORKERS))
    w.start()
    yield w
    w.stop()


def submit(store: JobStore, worker: RayJobWorker, spec: LoopSpec) -> str:
    record = store.create(spec.to_stored(), spec.lam)
    worker.submit(record.id)
    return record.id


def wait_until(store: JobStore, job_id: str, condition, timeout: float = 120.0) -> JobRecord:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        record = store.get(job_id)
        if condition(record):
            return record
        time.sleep(0.02)
    raise AssertionError(f"timed out; last record {store.get(job_id)}")


def slow_job(iterations: int = 8) -> LoopSpec:
    """Iterations long enough (each doubles the samples) that a test can act during one."""
    return LoopSpec(scene="cornell-box", width=64, height=64, spp_first=64, max_iterations=iterations)


def running_pids(worker: RayJobWorker, job_id: str, timeout: float = 60.0) -> list[int]:
    """The job's worker processes, once its actors exist (a claimed job starts them)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        pids = worker.worker_pids(job_id)
        if pids:
            return pids
        time.sleep(0.02)
    raise AssertionError(f"job {job_id} got no workers within {timeout} s: {worker.store.get(job_id)}")


def process_gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


def test_frames_split_into_contiguous_shares_no_bigger_than_one_apart():
    assert shares(5, 2) == [(0, 2), (2, 5)]
    assert shares(1, 2) == [(0, 1)]
    assert shares(4, 8) == [(0, 1), (1, 2), (2, 3), (3, 4)]


def test_two_jobs_run_at_the_same_time_on_two_workers(worker, store):
    ids = [submit(store, worker, slow_job(iterations=4)) for _ in range(2)]
    pids: dict[str, list[int]] = {}
    deadline = time.monotonic() + 60
    while len(pids) < 2 and time.monotonic() < deadline:  # both asked in turn: neither may end first
        pids.update({job_id: found for job_id in ids if job_id not in pids
                     for found in [worker.worker_pids(job_id)] if found})
        time.sleep(0.02)
    a, b = (wait_until(store, job_id, lambda r: r.finished) for job_id in ids)
    assert (a.state, b.state) == (COMPLETED, COMPLETED)
    assert a.started_at < b.finished_at and b.started_at < a.finished_at  # their run times overlap
    assert len(pids) == 2 and pids[ids[0]] != pids[ids[1]]  # each in its own worker process


def test_cancel_during_an_iteration_ends_its_worker_within_5_s_and_the_job_as_canceled(worker, store):
    job_id = submit(store, worker, slow_job(iterations=11))
    wait_until(store, job_id, lambda r: r.iteration >= 2)  # now inside a later iteration
    pids = running_pids(worker, job_id)
    started = time.monotonic()
    worker.cancel(job_id)
    while not all(process_gone(pid) for pid in pids) and time.monotonic() - started < 5.0:
        time.sleep(0.05)
    assert all(process_gone(pid) for pid in pids), "the job's workers still run 5 s after the cancel"
    # The record follows once the checkpoint's results are written, in a fresh worker (a process
    # start: seconds on a loaded machine).
    record = wait_until(store, job_id, lambda r: r.finished, timeout=60.0)
    assert record.state == CANCELED and record.stop_reason == "canceled", record.error
    assert record.iteration < 11


def test_stop_outwaits_a_job_still_starting_its_actors_and_leaves_it_queued(ray_runtime, store, tiny_networks,
                                                                          monkeypatch):
    """The race of a SIGTERM'd server: a driver thread still starting its job when stop() ran went
    on after stop() returned (on a server after ray.shutdown, where the actor it then created
    would start a fresh, unsealed local Ray). Its start is held here until stop()'s first wait is
    over; stop() must return only once the thread has left, the job requeued and no actor made."""
    w = RayJobWorker(store, tiny_networks, RaySettings(workers=WORKERS))
    starting = threading.Event()

    def film_size_held_past_stops_first_wait(*args, **kwargs):
        size = real_film_size(*args, **kwargs)
        starting.set()
        while w.health_problem() != "the server is stopping":
            time.sleep(0.02)
        time.sleep(2 * CANCEL_GRACE_SECONDS + 0.5)
        return size

    real_film_size = ray_worker.film_size
    monkeypatch.setattr(ray_worker, "film_size", film_size_held_past_stops_first_wait)
    w.start()
    job_id = submit(store, w, slow_job(iterations=2))
    assert starting.wait(120), store.get(job_id)
    w.stop()
    assert store.get(job_id).state == QUEUED  # the thread requeued it before stop() returned
    assert w.worker_pids(job_id) == []  # and started no actor


def test_a_cancel_mid_iteration_saves_the_checkpoints_results_in_a_worker_never_loading_the_scene_here(
        worker, store, monkeypatch):
    # eleven doubling iterations (up to 65 536 spp): far longer than any machine takes to cancel
    job_id = submit(store, worker, slow_job(iterations=11))
    wait_until(store, job_id, lambda r: r.iteration >= 2)  # inside a later iteration: its actors are busy

    def no_scene_here(*args, **kwargs):
        raise AssertionError("the API process built a RenderLoop (loaded the scene) for a cancel")

    monkeypatch.setattr(RenderLoop, "__init__", no_scene_here)  # this process is the server's
    worker.cancel(job_id)
    record = wait_until(store, job_id, lambda r: r.finished, timeout=30.0)
    assert record.state == CANCELED and record.error is None
    assert record.iteration >= 2 and record.stop_message.startswith(f"canceled after {record.iteration} iterations")
    result = read_exr(worker.files(job_id).result_path(0))  # the checkpoint's image, written by a worker
    assert result.spp.mean() == pytest.approx(record.spp)


def test_a_job_whose_lease_another_server_took_is_left_alone_without_another_write(worker, store, tmp_path):
    job_id = submit(store, worker, slow_job(iterations=11))
    wait_until(store, job_id, lambda r: r.iteration >= 2)
    running_pids(worker, job_id)
    # What another server does once this one's lease lapsed (a stall): the job is its own now.
    with sqlite3.connect(tmp_path / "data" / "jobs.sqlite") as db:
        db.execute("UPDATE jobs SET lease_owner = 'another-server' WHERE id = ?", (job_id,))
    taken = store.get(job_id)
    deadline = time.monotonic() + 60.0
    while worker.worker_pids(job_id) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert worker.worker_pids(job_id) == [], "this server still renders a job another server holds"
    stopped = store.get(job_id)
    time.sleep(2.0)  # nothing more is written from here on
    after = store.get(job_id)
    assert after == stopped and (after.state, after.lease_owner) == ("running", "another-server")
    # at most the iteration that had renewed the lease before it was taken
    assert after.iteration <= taken.iteration + 1


def test_a_worker_killed_mid_job_resumes_on_another_from_its_checkpoint(worker, store):
    job_id = submit(store, worker, slow_job(iterations=5))
    wait_until(store, job_id, lambda r: r.iteration >= 2)
    (pid,) = running_pids(worker, job_id)
    os.kill(pid, signal.SIGKILL)
    record = wait_until(store, job_id, lambda r: r.finished)
    assert (record.state, record.iteration, record.stop_reason) == (COMPLETED, 5, "max_iterations")
    assert record.resumed_from is not None and record.resumed_from >= 2  # not from scratch
    assert process_gone(pid)
    assert worker.files(job_id).result_path(0).is_file()


def big_texture_scene(folder: Path) -> Path:
    """A 16² film whose 8192² texture (a 0.2 MB PNG) takes ~0.8 GB once loaded: the job's memory
    estimate (its film size) knows nothing of it."""
    folder.mkdir(parents=True, exist_ok=True)
    Image.new("RGB", (8192, 8192), (128, 100, 90)).save(folder / "big.png")
    scene = folder / "scene.xml"
    scene.write_text("""<scene version="3.0.0">
  <integrator type="path"/>
  <sensor type="perspective"><float name="fov" value="40"/>
    <transform name="to_world"><lookat origin="0, 0, 5" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/></film></sensor>
  <emitter type="constant"/>
  <shape type="sphere"><bsdf type="diffuse">
    <texture type="bitmap" name="reflectance"><string name="filename" value="big.png"/></texture></bsdf></shape>
</scene>""")
    return scene


def test_a_job_over_its_memory_share_fails_with_a_clear_message_and_the_next_job_runs(worker, store, tmp_path):
    greedy = submit(store, worker, LoopSpec(scene=str(big_texture_scene(tmp_path / "greedy")), spp_first=4,
                                            max_iterations=2))
    failed = wait_until(store, greedy, lambda r: r.finished)
    assert failed.state == FAILED
    assert "over its memory share" in failed.error and "GiB" in failed.error, failed.error
    after = submit(store, worker, LoopSpec(scene="cornell-box", width=16, height=16, spp_first=4, max_iterations=2))
    assert wait_until(store, after, lambda r: r.finished).state == COMPLETED


def assert_timed_in_an_actor(applied) -> None:
    """The edit's timings (the PUT's Server-Timing) split the backend's call into the actor's own
    re-denoise and the hop around it, both inside the call the edit waited for."""
    t = applied.timings
    assert t["denoise"] >= t["tail"] > 0 and t["hop"] > 0, t
    assert t["relambda"] >= t["denoise"] + t["hop"] - 1e-3 and t["edit"] >= t["relambda"], t


def test_lambda_edits_on_a_running_job_rerun_only_the_cached_tail_in_its_worker(worker, store):
    job_id = submit(store, worker, slow_job())
    record = wait_until(store, job_id, lambda r: r.iteration >= 1)
    lam = np.full((64, 64), 3.0, dtype=np.float32)
    applied = worker.set_lambda(job_id, lam, 3.0)
    assert store.get(job_id).state == RUNNING  # answered by the job's actor, not a rebuilt loop
    assert (applied.full_passes, applied.tail_passes) == (0, 1)
    assert applied.version > record.preview_version
    assert_timed_in_an_actor(applied)
    preview = worker.load_preview(job_id, 0)  # the API's read: a λ edit's from memory until written
    assert preview.version >= applied.version and np.all(preview.layers["lambda"] == 3.0)
    worker.cancel(job_id)
    wait_until(store, job_id, lambda r: r.finished)


def test_lambda_edits_on_a_finished_job_run_in_a_ray_worker_never_loading_the_scene_here(worker, store,
                                                                                          monkeypatch):
    job_id = submit(store, worker, LoopSpec(scene="cornell-box", width=32, height=32, spp_first=16, max_iterations=2))
    done = wait_until(store, job_id, lambda r: r.finished)
    assert done.state == COMPLETED

    def no_scene_here(*args, **kwargs):
        raise AssertionError("the API process built a RenderLoop (loaded the scene) for a λ edit")

    monkeypatch.setattr(RenderLoop, "__init__", no_scene_here)  # this process is the server's
    first = worker.set_lambda(job_id, np.full((32, 32), 3.0, dtype=np.float32), 3.0)
    assert first.full_passes == 1  # the checkpoint reopened in a worker: its features cache rebuilt once
    second = worker.set_lambda(job_id, np.full((32, 32), 5.0, dtype=np.float32), 5.0)
    assert (second.full_passes, second.tail_passes) == (0, 1)  # that worker stayed warm
    assert_timed_in_an_actor(second)
    assert second.version > first.version > done.preview_version
    preview = worker.load_preview(job_id, 0)  # the API's read: a λ edit's from memory until written
    assert preview.version == second.version and np.all(preview.layers["lambda"] == 5.0)
    result = read_exr(worker.result_path(job_id, 0))  # the result follows λ, saved by the worker
    np.testing.assert_array_equal(result.lam, np.full((32, 32), 5.0, dtype=np.float32))


def test_a_sequence_fanned_out_over_two_workers_equals_the_single_process_result(worker, store, tiny_networks):
    spec = LoopSpec(scene="cornell-box-orbit", width=24, height=24, frames=3, spp_first=4, max_iterations=4)
    job_id = submit(store, worker, spec)
    pids: set[int] = set()
    while not store.get(job_id).finished:
        pids |= set(worker.worker_pids(job_id))  # the group's actors start one after the other
        time.sleep(0.02)
    assert store.get(job_id).state == COMPLETED
    assert len(pids) == 2  # the frames were shared between two worker processes
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as in the workers (one CPU each): the same float sums
    try:
        loop = RenderLoop(spec, tiny_networks)
        list(loop.run())
        expected = loop.result_frames()
    finally:
        torch.set_num_threads(threads)
    for f, want in enumerate(expected):
        got = read_exr(worker.files(job_id).result_path(f))
        np.testing.assert_array_equal(got.spp, want.spp, err_msg=f"frame {f}: another allocation")
        # Equal up to the last bits of float32, not bit for bit: the renderer's scatter-adds and
        # the GEMMs sum in an order that can differ between processes (seen on an AVX2 EPYC,
        # 1 ulp in the noisy mean of one frame), which a bitwise check would call a mismatch.
        for layer in ("color", "noisy", "variance", "error", "motion"):
            if getattr(want, layer) is None:
                assert getattr(got, layer) is None, f"frame {f} {layer}"
                continue
            np.testing.assert_allclose(getattr(got, layer), getattr(want, layer), rtol=1e-5, atol=1e-6,
                                       err_msg=f"frame {f} {layer}")

