"""Persistence: `kill -9` the server mid-job, start another on the same data dir."""
from __future__ import annotations

import signal
import time

import httpx
import numpy as np

from iteration_hold import ENV as HOLD, hold_value
from service.exr import read_exr
from service_harness import finished, wait_for

ITERATIONS = 4  # 16 → 128 spp
SIZE = 32
# The first server's job holds inside its third iteration's render (iteration_hold.py): it is
# running at the kill or SIGTERM however fast or slow the machine, and renders nothing meanwhile.
HELD_AFTER_TWO = {HOLD: hold_value(2)}


def test_kill_9_mid_job_resumes_from_its_checkpoint(start_server, tmp_path):
    first = start_server(env=HELD_AFTER_TWO)
    with httpx.Client(base_url=first.url, timeout=60) as client:
        body = {"scene": "cornell-box", "width": SIZE, "height": SIZE, "max_iterations": ITERATIONS}
        job_id = client.post("/jobs", json=body).json()["id"]
        queued_id = client.post("/jobs", json={**body, "width": 16, "height": 16, "max_iterations": 2}).json()["id"]
        wait_for(client, job_id, lambda job: job["iteration"] >= 2)
        rects = {"rects": [{"x": 0, "y": 0, "w": SIZE // 2, "h": SIZE, "value": 3.0}]}
        assert client.put(f"/jobs/{job_id}/lambda", json=rects).status_code == 200
        at_kill = client.get(f"/jobs/{job_id}").json()
    first.kill()
    assert at_kill["state"] == "running" and at_kill["iteration"] < ITERATIONS, "job ended before the kill"

    second = start_server(first.data_dir)
    with httpx.Client(base_url=second.url, timeout=60) as client:
        final = wait_for(client, job_id, finished, timeout=300)
        assert final["state"] == "completed", final
        assert final["iteration"] == ITERATIONS and final["spp"] == 16 * 2 ** (ITERATIONS - 1)
        # Resumed where the last checkpoint left it (never from scratch), with its λ map.
        assert final["resumed_from"] is not None and final["resumed_from"] >= at_kill["iteration"] >= 2
        assert final["started_at"] == at_kill["started_at"]
        expected = np.ones((SIZE, SIZE), np.float32)
        expected[:, :SIZE // 2] = 3.0
        result = tmp_path / "result.exr"
        result.write_bytes(client.get(f"/jobs/{job_id}/result.exr").content)
        frame = read_exr(result)
        np.testing.assert_array_equal(frame.lam, expected)
        assert frame.spp.mean() == 16 * 2 ** (ITERATIONS - 1)

        # The job queued behind it runs after the restart too.
        assert wait_for(client, queued_id, finished)["state"] == "completed"
        # This server finished the job itself: its loop is still warm, λ is a tail pass.
        warm = client.put(f"/jobs/{job_id}/lambda", json={"value": 4.0}).json()
        assert warm["full_passes"] == 0 and warm["tail_passes"] == 1
    second.stop()

    third = start_server(first.data_dir)
    with httpx.Client(base_url=third.url, timeout=60) as client:
        # λ on a finished job after a restart: the features cache is rebuilt once, then λ-only.
        first_change = client.put(f"/jobs/{job_id}/lambda", json={"value": 2.0}).json()
        assert first_change["full_passes"] == 1
        second_change = client.put(f"/jobs/{job_id}/lambda", json={"value": 5.0}).json()
        assert second_change["full_passes"] == 0 and second_change["tail_passes"] == 1
        assert second_change["version"] > first_change["version"] > warm["version"]


def test_finished_jobs_survive_a_restart(start_server):
    first = start_server()
    with httpx.Client(base_url=first.url, timeout=60) as client:
        body = {"scene": "cornell-box", "width": 16, "height": 16, "max_iterations": 2,
                "denoise": False, "allocator": "uniform"}
        job_id = client.post("/jobs", json=body).json()["id"]
        before = wait_for(client, job_id, finished)
        result = client.get(f"/jobs/{job_id}/result.exr").content
    first.stop()
    second = start_server(first.data_dir)
    with httpx.Client(base_url=second.url, timeout=60) as client:
        after = client.get(f"/jobs/{job_id}").json()
        assert after == before
        assert client.get(f"/jobs/{job_id}/result.exr").content == result
        assert client.get(f"/jobs/{job_id}/preview").status_code == 200


def test_sigterm_requeues_a_running_job_exits_fast_and_the_next_start_completes_it(start_server):
    # Held inside a render: the shutdown stops it through the loop's per-chunk check (a real
    # render's interruption by SIGTERM: tests/service/test_shutdown.py, `renderloop serve` itself).
    first = start_server(env=HELD_AFTER_TWO)
    with httpx.Client(base_url=first.url, timeout=60) as client:
        body = {"scene": "cornell-box", "width": SIZE, "height": SIZE, "max_iterations": ITERATIONS}
        job_id = client.post("/jobs", json=body).json()["id"]
        at_term = wait_for(client, job_id, lambda job: job["iteration"] >= 2)
        with client.stream("GET", f"/jobs/{job_id}/events") as events:  # an open stream must not hold shutdown
            next(events.iter_lines())
            started = time.monotonic()
            first.process.send_signal(signal.SIGTERM)
            first.process.wait(30)
    exit_seconds = time.monotonic() - started
    assert at_term["state"] == "running" and at_term["iteration"] < ITERATIONS, "job ended before SIGTERM"
    assert exit_seconds < 15, f"shutdown took {exit_seconds:.1f} s"

    second = start_server(first.data_dir)
    with httpx.Client(base_url=second.url, timeout=60) as client:
        final = wait_for(client, job_id, finished, timeout=300)
        assert final["state"] == "completed" and final["iteration"] == ITERATIONS
        # Resumed from a checkpoint, never from scratch: at most the in-flight iteration was redone.
        assert final["resumed_from"] is not None and final["resumed_from"] >= at_term["iteration"]
        assert final["spp"] == 16 * 2 ** (ITERATIONS - 1)
    second.stop()


def test_delete_cancels_a_running_job_and_removes_its_record_and_files(start_server):
    server = start_server(env={HOLD: hold_value(1)})
    with httpx.Client(base_url=server.url, timeout=60) as client:
        body = {"scene": "cornell-box", "width": SIZE, "height": SIZE, "max_iterations": ITERATIONS}
        job_id = client.post("/jobs", json=body).json()["id"]
        wait_for(client, job_id, lambda job: job["iteration"] >= 1)
        assert client.delete(f"/jobs/{job_id}").status_code == 204
        assert client.get(f"/jobs/{job_id}").status_code == 404
        assert client.delete(f"/jobs/{job_id}").status_code == 404
        assert not (server.data_dir / "jobs" / job_id).exists()
    server.stop()
