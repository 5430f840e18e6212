"""Job leases with TWO real `renderloop serve` processes on ONE real PostgreSQL and one shared
data dir (thread backend): a server starting beside a live one leaves its running job alone;
when that server is killed (-9) mid-job its lease lapses and the other server resumes the job
from the dead one's checkpoint and finishes it."""
from __future__ import annotations

import time

import httpx
import psycopg

from service_harness import Server, finished, wait_for

LEASE_SECONDS = 2  # renewed every 2/3 s; a dead server's job is requeued within ~3 s
ITERATIONS = 8  # 16 → 2048 spp at 64²: still running after the second server's start-up
FINISH_SECONDS = 240  # generous: a loaded 2-core machine


def test_a_job_whose_server_is_killed_is_resumed_by_the_other_server_from_its_checkpoint(tmp_path, postgres_url):
    env = {"RENDERLOOP_DB": postgres_url, "RENDERLOOP_LEASE_SECONDS": str(LEASE_SECONDS),
           "RENDERLOOP_CONCURRENCY": "1"}
    data = tmp_path / "data"
    first = Server(data, tmp_path / "first.log", env=env).start()
    second = Server(data, tmp_path / "second.log", env=env)
    try:
        with httpx.Client(base_url=first.url, timeout=60) as a:
            body = {"scene": "cornell-box", "width": 64, "height": 64, "max_iterations": ITERATIONS}
            job_id = a.post("/jobs", json=body).json()["id"]
            wait_for(a, job_id, lambda job: job["iteration"] >= 1)
        owner, expires = lease(postgres_url, job_id)
        assert owner.split("/")[1] == str(first.process.pid)  # host/pid/nonce of the first server
        second.start()  # its start-up must not take the live server's job
        with httpx.Client(base_url=second.url, timeout=60) as b:
            at_kill = wait_for(b, job_id, lambda job: job["iteration"] >= 2)
            assert at_kill["state"] == "running" and at_kill["resumed_from"] is None, at_kill
            renewed_owner, renewed = lease(postgres_url, job_id)
            assert renewed_owner == owner and renewed > expires  # still the first server's, renewed
            first.kill()
            killed_at = time.monotonic()
            final = wait_for(b, job_id, finished, timeout=FINISH_SECONDS)
            took = time.monotonic() - killed_at
            assert final["state"] == "completed", final
            assert final["iteration"] == ITERATIONS and final["spp"] == 16 * 2 ** (ITERATIONS - 1)
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
