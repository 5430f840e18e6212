"""POST /jobs admission on a real `renderloop serve` process (thread backend, one render thread):
the queue caps per client and per server (429 + Retry-After), queued bundles counted in the
disk cap (507), the Idempotency-Key (a retried POST gives the first job back, never a second),
and priority (the highest-priority queued job starts first)."""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Iterator

import httpx
import pytest

from iteration_hold import ENV as HOLD, hold_value
from service_harness import Server, finished, wait_for, zip_bytes

# Holds the one render thread while a test fills the queue behind it, however slow the uploads:
# its seed is the one the servers here hold inside its first render (iteration_hold.py), rendering
# nothing meanwhile; canceled at the end of each test (the cancel ends the hold).
BLOCKER_SEED = 7
BLOCKER = {"scene": "cornell-box", "width": 16, "height": 16, "max_iterations": 2, "seed": BLOCKER_SEED}
SMALL = {"scene": "cornell-box", "width": 16, "height": 16, "max_iterations": 1, "denoise": False,
         "allocator": "uniform"}
TINY_SCENE = ('<scene version="3.0.0"><sensor type="perspective"><film type="hdrfilm"><integer name="width" '
              'value="8"/><integer name="height" value="8"/></film></sensor><shape type="sphere"/>'
              '<emitter type="constant"/></scene>')


@pytest.fixture
def serve(tmp_path) -> Iterator:
    servers: list[Server] = []

    def start(**env: str) -> Server:
        server = Server(tmp_path / "data", tmp_path / f"server{len(servers)}.log",
                        env={HOLD: hold_value(0, BLOCKER_SEED), **env})
        servers.append(server)
        return server.start()

    yield start
    for server in servers:
        server.stop()


def client_from(server: Server, address: str = "127.0.0.1") -> httpx.Client:
    """A client whose connections come from `address` (any 127.x address reaches the loopback
    server): without a token, that address is who the per-client cap counts."""
    # No kept-alive connections: one the server closes as idle just as it is reused reads as a reset.
    transport = httpx.HTTPTransport(local_address=address, limits=httpx.Limits(max_keepalive_connections=0))
    return httpx.Client(base_url=server.url, timeout=60, transport=transport)


def hold_the_render_thread(client: httpx.Client) -> str:
    """Start a long job and wait until it runs: queued jobs after it stay queued."""
    job_id = client.post("/jobs", json=BLOCKER).json()["id"]
    wait_for(client, job_id, lambda job: job["state"] == "running")
    return job_id


def test_beyond_the_per_client_and_the_per_server_queue_caps_a_submit_gets_429_with_retry_after(serve):
    server = serve(RENDERLOOP_MAX_QUEUED="3", RENDERLOOP_MAX_QUEUED_PER_CLIENT="2")
    with client_from(server) as first, client_from(server, "127.0.0.2") as second:
        blocker = hold_the_render_thread(first)
        assert [first.post("/jobs", json=SMALL).status_code for _ in range(2)] == [202, 202]
        refused = first.post("/jobs", json=SMALL)
        assert refused.status_code == 429 and int(refused.headers["retry-after"]) > 0
        assert "per client is 2" in refused.json()["detail"]
        assert second.post("/jobs", json=SMALL).status_code == 202  # another client still has room
        full = second.post("/jobs", json=SMALL)
        assert full.status_code == 429 and "queue is full" in full.json()["detail"]
        assert int(full.headers["retry-after"]) > 0
        states = [job["state"] for job in first.get("/jobs").json()["jobs"]]
        assert sorted(states) == ["queued"] * 3 + ["running"]  # nothing refused was stored
        first.post(f"/jobs/{blocker}/cancel")


def test_a_retried_post_with_the_same_idempotency_key_gives_the_first_job_and_no_second(serve):
    server = serve(RENDERLOOP_MAX_QUEUED_PER_CLIENT="1")
    with client_from(server) as client:
        blocker = hold_the_render_thread(client)
        first = client.post("/jobs", json=SMALL, headers={"Idempotency-Key": "upload-42"})
        assert first.status_code == 202
        # The retry finds the queue full for this client: it still gets its job, not a 429.
        again = client.post("/jobs", json=SMALL, headers={"Idempotency-Key": "upload-42"})
        assert again.status_code == 200 and again.json()["id"] == first.json()["id"]
        other = client.post("/jobs", json=SMALL, headers={"Idempotency-Key": "upload-43"})
        assert other.status_code == 429  # a new key is a new job, under the cap
        assert len(client.get("/jobs").json()["jobs"]) == 2
        bad = client.post("/jobs", json=SMALL, headers={"Idempotency-Key": "x" * 300})
        assert bad.status_code == 422 and "Idempotency-Key" in bad.json()["detail"]
        client.post(f"/jobs/{blocker}/cancel")


def upload(client: httpx.Client, payload: bytes) -> httpx.Response:
    archive = zip_bytes({"scene.xml": TINY_SCENE, "payload.bin": payload})
    return client.post("/jobs", data={"spec": json.dumps({"scene": "scene.xml", "max_iterations": 1})},
                       files={"bundle": ("b.zip", archive, "application/zip")})


def test_queued_bundles_count_in_the_disk_cap_and_a_submit_beyond_it_gets_507(serve, tmp_path):
    bundle_mib, cap_mib = 6, 15  # two queued bundles fit, a third would not
    server = serve(RENDERLOOP_MAX_DISK_GB=str(cap_mib / 1024))
    with client_from(server) as client:
        blocker = hold_the_render_thread(client)
        accepted = [upload(client, os.urandom(bundle_mib * 2**20)) for _ in range(2)]
        assert [r.status_code for r in accepted] == [202, 202], [r.text for r in accepted]
        assert client.get(f"/jobs/{blocker}").json()["state"] == "running"  # so both uploads are still queued
        refused = upload(client, os.urandom(bundle_mib * 2**20))
        assert refused.status_code == 507 and "data folder is full" in refused.json()["detail"]
        jobs_dir = Path(tmp_path / "data" / "jobs")
        assert sorted(p.name for p in jobs_dir.iterdir()) == sorted([blocker, *(r.json()["id"] for r in accepted)])
        client.post(f"/jobs/{blocker}/cancel")


def test_the_highest_priority_queued_job_starts_first_and_the_record_shows_it(serve):
    server = serve()
    with client_from(server) as client:
        blocker = hold_the_render_thread(client)
        ids = {p: client.post("/jobs", json={**SMALL, "priority": p}).json()["id"] for p in (0, 5, -3)}
        assert client.get(f"/jobs/{ids[5]}").json()["priority"] == 5
        assert client.post("/jobs", json={**SMALL, "priority": 101}).status_code == 422
        client.post(f"/jobs/{blocker}/cancel")
        done = {p: wait_for(client, job_id, finished, timeout=300) for p, job_id in ids.items()}
        assert all(job["state"] == "completed" for job in done.values()), done
        starts = sorted(done, key=lambda p: done[p]["started_at"])
        assert starts == [5, 0, -3]
