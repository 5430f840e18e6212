"""Job leases with TWO real `renderloop serve` processes on ONE real PostgreSQL and one shared
data dir (thread backend): a server starting beside a live one leaves its running job alone;
when that server is killed (-9) mid-job its lease lapses and the other server resumes the job
from the dead one's checkpoint and finishes it."""
from __future__ import annotations

import signal
import time

import httpx
import psycopg
import pytest

from iteration_hold import ENV as HOLD, hold_value
from service_harness import Server, finished, wait_for

LEASE_SECONDS = 2  # renewed every 2/3 s; a dead server's job is requeued within ~3 s
ITERATIONS = 8  # 16 → 2048 spp at 64²: still running after the second server's start-up (the stall test)
HELD_ITERATIONS = 4  # the kill -9 test's job, held by the first server inside its third render
FINISH_SECONDS = 240  # generous: a loaded 2-core machine


def test_a_job_whose_server_is_killed_is_resumed_by_the_other_server_from_its_checkpoint(tmp_path, postgres_url):
    env = {"RENDERLOOP_DB": postgres_url, "RENDERLOOP_LEASE_SECONDS": str(LEASE_SECONDS),
           "RENDERLOOP_CONCURRENCY": "1"}
    data = tmp_path / "data"
    # The first server holds the job inside its third render (iteration_hold.py): still running at
    # the kill however fast the machine, and no rendering meanwhile; the second one renders as written.
    first = Server(data, tmp_path / "first.log", env={**env, HOLD: hold_value(2)}).start()
    second = Server(data, tmp_path / "second.log", env=env)
    try:
        with fresh_client(first) as a:
            body = {"scene": "cornell-box", "width": 32, "height": 32, "max_iterations": HELD_ITERATIONS}
            job_id = a.post("/jobs", json=body).json()["id"]
            wait_for(a, job_id, lambda job: job["iteration"] >= 1)
        owner, expires = lease(postgres_url, job_id)
        assert owner.split("/")[1] == str(first.process.pid)  # host/pid/nonce of the first server
        second.start()  # its start-up must not take the live server's job
        with fresh_client(second) as b:
            at_kill = wait_for(b, job_id, lambda job: job["iteration"] >= 2)
            assert at_kill["state"] == "running" and at_kill["resumed_from"] is None, at_kill
            renewed_owner, renewed = lease(postgres_url, job_id)
            assert renewed_owner == owner and renewed > expires  # still the first server's, renewed
            first.kill()
            killed_at = time.monotonic()
            final = wait_for(b, job_id, finished, timeout=FINISH_SECONDS)
            took = time.monotonic() - killed_at
            assert final["state"] == "completed", final
            assert final["iteration"] == HELD_ITERATIONS and final["spp"] == 16 * 2 ** (HELD_ITERATIONS - 1)
            # Resumed where the dead server's last checkpoint left it, never from scratch.
            assert final["resumed_from"] is not None and final["resumed_from"] >= at_kill["iteration"] >= 2
            assert final["started_at"] == at_kill["started_at"]
            assert b.get(f"/jobs/{job_id}/result.exr").status_code == 200
        assert f"job {job_id}: its server's lease lapsed" in second.log()
        assert lease(postgres_url, job_id)[0].split("/")[1] == str(second.process.pid)
        print(f"killed at iteration {at_kill['iteration']}; the other server finished {took:.1f} s later")
    finally:
        first.kill()
        second.stop()


def lease(url: str, job_id: str) -> tuple[str, float]:
    """The job's lease as the database holds it: owner and expiry."""
    with psycopg.connect(url) as conn:
        return conn.execute("SELECT lease_owner, lease_expires_at FROM jobs WHERE id = %s", (job_id,)).fetchone()


@pytest.mark.slow  # ~40 s: two servers and a job long enough to outlive a stall; the kill -9 test covers the default run
def test_a_server_that_stalls_past_its_lease_stops_its_copy_and_leaves_the_job_to_the_one_that_took_it(
        tmp_path, postgres_url):
    """SIGSTOP (a frozen VM, a long GC pause) past the lease: the other server resumes the job;
    when the stalled one wakes up it must not write a checkpoint, a record or an end state."""
    env = {"RENDERLOOP_DB": postgres_url, "RENDERLOOP_LEASE_SECONDS": str(LEASE_SECONDS),
           "RENDERLOOP_CONCURRENCY": "1"}
    data = tmp_path / "data"
    first = Server(data, tmp_path / "first.log", env=env).start()
    second = Server(data, tmp_path / "second.log", env=env)
    try:
        with fresh_client(first) as a:
            body = {"scene": "cornell-box", "width": 64, "height": 64, "max_iterations": ITERATIONS}
            job_id = a.post("/jobs", json=body).json()["id"]
            wait_for(a, job_id, lambda job: job["iteration"] >= 1)
        second.start()
        with fresh_client(second) as b:
            first.process.send_signal(signal.SIGSTOP)
            deadline = time.monotonic() + FINISH_SECONDS
            while lease(postgres_url, job_id)[0].split("/")[1] != str(second.process.pid):
                assert time.monotonic() < deadline, "the second server never took the job over"
                time.sleep(0.2)
            first.process.send_signal(signal.SIGCONT)
            final = wait_for(b, job_id, finished, timeout=FINISH_SECONDS)
            assert final["state"] == "completed" and final["iteration"] == ITERATIONS, final
            assert final["resumed_from"] is not None
        deadline = time.monotonic() + 30
        while "lost its lease" not in first.log():
            assert time.monotonic() < deadline, first.log()
            time.sleep(0.2)
        assert first.process.poll() is None  # the stalled server lives on, it only let the job go
    finally:
        if first.process is not None and first.process.poll() is None:
            first.process.send_signal(signal.SIGCONT)
        first.kill()
        second.stop()


def fresh_client(server: Server) -> httpx.Client:
    """No kept-alive connections: this test waits on the database for seconds between requests,
    and a connection the server closes as idle (serve --keep-alive-timeout) at the moment the
    client reuses it would read as a reset."""
    return httpx.Client(base_url=server.url, timeout=60, limits=httpx.Limits(max_keepalive_connections=0))
