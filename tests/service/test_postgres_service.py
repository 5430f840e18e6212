"""`renderloop serve` with its job records in a real PostgreSQL server (RENDERLOOP_DB): a job
completes, its files land in the data dir, a lost database connection is a 503 then heals,
and a restarted server still lists the job."""
from __future__ import annotations

import httpx

from service_harness import Server, finished, wait_for


def test_a_server_on_postgresql_completes_a_job_and_a_restarted_one_still_lists_it(tmp_path, postgres_server,
                                                                                   postgres_url):
    data = tmp_path / "data"
    env = {"RENDERLOOP_DB": postgres_url}
    first = Server(data, tmp_path / "first.log", env=env).start()
    try:
        with httpx.Client(base_url=first.url, timeout=60) as client:
            body = {"scene": "cornell-box", "width": 16, "height": 16, "max_iterations": 1}
            job_id = client.post("/jobs", json=body).json()["id"]
            done = wait_for(client, job_id, finished)
            assert done["state"] == "completed", done
            assert postgres_server.drop_connections(postgres_url) == 1  # the server's one connection
            lost = client.get(f"/jobs/{job_id}")
            assert lost.status_code == 503 and lost.headers["retry-after"] == "5"
            assert "postgresql" not in lost.text  # the database's address stays in the log
            assert client.get(f"/jobs/{job_id}").json()["state"] == "completed"  # reconnected
    finally:
        first.stop()
    assert not (data / "jobs.sqlite").exists()  # the records are in PostgreSQL, the files on disk
    assert (data / "jobs" / job_id).is_dir()

    second = Server(data, tmp_path / "second.log", env=env).start()
    try:
        with httpx.Client(base_url=second.url, timeout=60) as client:
            listed = client.get("/jobs").json()["jobs"]
            assert [(j["id"], j["state"], j["iteration"]) for j in listed] == [(job_id, "completed", 1)]
            result = client.get(f"/jobs/{job_id}/result.exr")
            assert result.status_code == 200 and len(result.content) > 0
    finally:
        second.stop()
